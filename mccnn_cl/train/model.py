"""The MC-CNN networks as one torch module, the architecture a parameter.

``mccnn-paper`` (CVPR 2015): L1 conv 5x5 (1 -> 32), L2 5x5 (32 -> 200), L3
1x1 (200 -> 200), ReLU after each, tied between the left and right patch;
concatenation; fc 300 x4 with ReLU; 2 outputs (softmax logits over {bad
match = 0, good match = 1}); cost = softmax[0].
``mccnn-fst`` (JMLR 2016): conv k x k with ReLU *between* layers (none after
the last), features L2-normalised per pixel (x / sqrt(|x|^2 + 1e-5), the
released ``Normalize2``); the head is the score s = f_L . f_R; cost = -s.
``mccnn-acrt``: conv with ReLU after each, concatenation, fc with ReLU
between, 1 output; cost = sigmoid(output) = P(bad match) (trained with BCE,
target 0 for the matching pair and 1 for the mismatch, as the released code).

All convolutions are valid and there is no pooling, so the same module runs
on patches (:meth:`MCCNN.forward`) and fully convolutionally on whole images
or crops (:meth:`MCCNN.features`): a patch's feature vector equals the
feature map at the patch centre.  :meth:`MCCNN.loss` holds the three
training losses (paper CE, fst hinge max(0, m + s- - s+), acrt BCE).
"""

from __future__ import annotations

import torch
from torch import nn

import torch.nn.functional as F

from mccnn_cl.weights import ACRT, ARCHITECTURES, FC_OUTPUTS, FST, PAPER, PAPER_CONV, PAPER_FC, Weights

#: default layers per architecture (KITTI variants of the JMLR networks)
DEFAULT_LAYERS = {PAPER: (PAPER_CONV, PAPER_FC), FST: ([[64, 3]] * 4, []),
                  ACRT: ([[112, 3]] * 4, [384, 384, 384, 384, 1])}
NORM_EPS = 1e-5


class MCCNN(nn.Module):
    """Siamese MC-CNN. ``conv_layers``: [[maps, kernel], ...]; ``fc_layers``: [units, ..., outputs]."""

    def __init__(self, conv_layers=None, fc_layers=None, input_channels: int = 1,
                 architecture: str = PAPER, margin: float = 0.2):
        super().__init__()
        if architecture not in ARCHITECTURES:
            raise ValueError(f"unknown architecture {architecture!r}")
        dconv, dfc = DEFAULT_LAYERS[architecture]
        conv_layers = [list(c) for c in (conv_layers or dconv)]
        fc_layers = list(dfc if fc_layers is None else fc_layers)
        if architecture == FST and fc_layers:
            raise ValueError("an mccnn-fst network has no fc layers")
        if architecture != FST and (not fc_layers or fc_layers[-1] != FC_OUTPUTS[architecture]):
            raise ValueError(f"the last fc layer of {architecture} must have {FC_OUTPUTS[architecture]} outputs")
        self.architecture, self.margin = architecture, margin
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

    def raw_features(self, x: torch.Tensor) -> torch.Tensor:
        """The conv stack before fst's normalisation: (N, C, H, W) -> (N, maps, H - P + 1, W - P + 1)."""
        last = len(self.convs) - 1
        for i, conv in enumerate(self.convs):
            x = conv(x)
            if i < last or self.architecture != FST:
                x = torch.relu(x)
        return x

    @staticmethod
    def l2_normalise(x: torch.Tensor, dim: int) -> torch.Tensor:
        """x / sqrt(sum x^2 + 1e-5) along ``dim`` (the released Normalize2)."""
        return x / torch.sqrt((x * x).sum(dim=dim, keepdim=True) + NORM_EPS)

    def finish(self, f: torch.Tensor, dim: int) -> torch.Tensor:
        """fst: normalise raw features along the channel axis ``dim``; others: unchanged."""
        return self.l2_normalise(f, dim) if self.architecture == FST else f

    def features(self, x: torch.Tensor) -> torch.Tensor:
        """Per-pixel features (normalised for fst): (N, C, H, W) -> (N, maps, H - P + 1, W - P + 1)."""
        return self.finish(self.raw_features(x), 1)

    def head(self, fl: torch.Tensor, fr: torch.Tensor) -> torch.Tensor:
        """Feature vectors (..., maps) x2 -> paper logits (..., 2), fst score (...), acrt logit (...)."""
        if self.architecture == FST:
            return (fl * fr).sum(-1)
        x = torch.cat([fl, fr], dim=-1)
        for i, fc in enumerate(self.fcs):
            x = fc(x)
            if i < len(self.fcs) - 1:
                x = torch.relu(x)
        return x[..., 0] if self.architecture == ACRT else x

    def cost(self, out: torch.Tensor) -> torch.Tensor:
        """Matching cost from :meth:`head` outputs (low = good match)."""
        if self.architecture == PAPER:
            return torch.softmax(out, dim=-1)[..., 0]
        if self.architecture == FST:
            return -out
        return torch.sigmoid(out)

    def loss(self, out_pos: torch.Tensor, out_neg: torch.Tensor, reduction: str = "mean") -> torch.Tensor:
        """Training loss on head outputs of paired positives and negatives (same length).

        paper: cross-entropy (class 1 = good match); fst: hinge
        max(0, margin + s- - s+) per pair; acrt: BCE of sigmoid(out), target 0
        for the positive and 1 for the negative.  ``reduction="sum"`` sums
        over examples (fst: over pairs), for evaluation.
        """
        if self.architecture == FST:
            per = torch.relu(self.margin + out_neg - out_pos)
            return per.mean() if reduction == "mean" else per.sum()
        out = torch.cat([out_pos, out_neg])
        n = out_pos.shape[0]
        if self.architecture == PAPER:
            lab = torch.cat([torch.ones(n, dtype=torch.long), torch.zeros(n, dtype=torch.long)]).to(out.device)
            return F.cross_entropy(out, lab, reduction=reduction)
        tgt = torch.cat([torch.zeros(n), torch.ones(n)]).to(out.device, out.dtype)
        return F.binary_cross_entropy_with_logits(out, tgt, reduction=reduction)

    def forward(self, left: torch.Tensor, right: torch.Tensor) -> torch.Tensor:
        """Head outputs for patch pairs: left/right (N, C, P, P) -> (N, 2) paper, (N,) fst/acrt."""
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
        return Weights(conv=conv, fc=fc, meta=dict(meta or {}), architecture=self.architecture).validate()

    @classmethod
    def from_weights(cls, w: Weights) -> "MCCNN":
        """Build a module holding the given weights (CPU, float32)."""
        m = cls(w.conv_layers(), w.fc_layers(), w.input_channels, architecture=w.architecture)
        with torch.no_grad():
            for c, (W, b) in zip(m.convs, w.conv):
                c.weight.copy_(torch.from_numpy(W))
                c.bias.copy_(torch.from_numpy(b))
            for f, (W, b) in zip(m.fcs, w.fc):
                f.weight.copy_(torch.from_numpy(W))
                f.bias.copy_(torch.from_numpy(b))
        return m
