"""The MC-CNN network of the CVPR 2015 paper as a torch module.

L1 conv 5x5 (1 -> 32), L2 5x5 (32 -> 200), L3 1x1 (200 -> 200), ReLU after
each, tied between the left and right patch; concatenation (400); L4..L7
fully connected with 300 units and ReLU; L8 with 2 outputs (logits of the
softmax over {bad match = 0, good match = 1}).

The same module runs on 9x9 patches (training) and fully convolutionally on
whole images (:meth:`MCCNN.features`), which is what the OpenCL side does.
"""

from __future__ import annotations

import torch
from torch import nn

from mccnn_cl.weights import PAPER_CONV, PAPER_FC, Weights


class MCCNN(nn.Module):
    """Siamese MC-CNN. ``conv_layers``: [[maps, kernel], ...]; ``fc_layers``: [units, ..., 2]."""

    def __init__(self, conv_layers=None, fc_layers=None, input_channels: int = 1):
        super().__init__()
        conv_layers = [list(c) for c in (conv_layers or PAPER_CONV)]
        fc_layers = list(fc_layers or PAPER_FC)
        if fc_layers[-1] != 2:
            raise ValueError("the last fc layer must have 2 outputs")
        self.conv_layers, self.fc_layers = conv_layers, fc_layers
        self.input_channels = input_channels
        convs, cin = [], input_channels
        for maps, k in conv_layers:
            convs.append(nn.Conv2d(cin, maps, k))
            cin = maps
        self.convs = nn.ModuleList(convs)
        fcs, fin = [], 2 * cin
        for out in fc_layers:
            fcs.append(nn.Linear(fin, out))
            fin = out
        self.fcs = nn.ModuleList(fcs)
        self.patch_size = 1 + sum(k - 1 for _, k in conv_layers)

    def he_init_(self) -> "MCCNN":
        """He (Kaiming normal, ReLU gain) weights and zero biases, in place.

        torch's default init (uniform, bound 1/sqrt(fan_in)) leaves this deep
        ReLU net stuck at the chance loss ln 2 for thousands of iterations at
        the paper's learning rate; He init starts learning at once.  Training
        calls this after seeding torch.
        """
        for mod in list(self.convs) + list(self.fcs):
            nn.init.kaiming_normal_(mod.weight, nonlinearity="relu")
            nn.init.zeros_(mod.bias)
        return self

    def features(self, x: torch.Tensor) -> torch.Tensor:
        """L1..L3 with ReLU: (N, C, H, W) -> (N, maps, H - P + 1, W - P + 1)."""
        for conv in self.convs:
            x = torch.relu(conv(x))
        return x

    def head(self, fl: torch.Tensor, fr: torch.Tensor) -> torch.Tensor:
        """L4..L8 on feature vectors (..., maps) x2 -> logits (..., 2)."""
        x = torch.cat([fl, fr], dim=-1)
        for i, fc in enumerate(self.fcs):
            x = fc(x)
            if i < len(self.fcs) - 1:
                x = torch.relu(x)
        return x

    def forward(self, left: torch.Tensor, right: torch.Tensor) -> torch.Tensor:
        """Logits for patch pairs: left/right (N, C, P, P) -> (N, 2)."""
        fl = self.features(left).flatten(1)
        fr = self.features(right).flatten(1)
        return self.head(fl, fr)

    # -- export / import ---------------------------------------------
    def to_weights(self, meta: dict | None = None) -> Weights:
        """Export to the :mod:`mccnn_cl.weights` format."""
        def np32(t):
            return t.detach().to("cpu", torch.float32).contiguous().numpy().copy()
        conv = [(np32(c.weight), np32(c.bias)) for c in self.convs]
        fc = [(np32(f.weight), np32(f.bias)) for f in self.fcs]
        return Weights(conv=conv, fc=fc, meta=dict(meta or {})).validate()

    @classmethod
    def from_weights(cls, w: Weights) -> "MCCNN":
        """Build a module holding the given weights (CPU, float32)."""
        m = cls(w.conv_layers(), w.fc_layers(), w.input_channels)
        with torch.no_grad():
            for c, (W, b) in zip(m.convs, w.conv):
                c.weight.copy_(torch.from_numpy(W))
                c.bias.copy_(torch.from_numpy(b))
            for f, (W, b) in zip(m.fcs, w.fc):
                f.weight.copy_(torch.from_numpy(W))
                f.bias.copy_(torch.from_numpy(b))
        return m
