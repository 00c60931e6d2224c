"""``mccnn-cl convert-weights`` and ``mccnn-cl models`` (wired into :mod:`mccnn_cl.cli`)."""

from __future__ import annotations

import os

from ..errors import InputError

KEY_SETTINGS = ("sgm_pi1", "sgm_pi2", "cbca_iterations", "blur_sigma")


def add_parsers(sub, parents) -> None:
    """Add the two sub-commands to the CLI's sub-parsers."""
    from ..importers import DATASETS

    c = sub.add_parser("convert-weights", parents=parents, help="convert a published network (.t7, .pt) to .npz",
                       description="Read a published MC-CNN network -- the authors' Torch7 .t7 (MC-CNN-fst) "
                                   "or CNES's PyTorch .pt (fast or accurate) -- check it and write it as a "
                                   "mccnn_cl weights file, with the stereo settings it was published with.")
    c.add_argument("input", metavar="IN", help="network file (.t7 or .pt/.pth)")
    c.add_argument("-o", "--output", metavar="OUT.npz", required=True, help="weights file to write")
    c.add_argument("--dataset", choices=DATASETS, default=None,
                   help="whose stereo settings the file carries (default: the dataset the file identifies: "
                        "a published network's, or a .t7's main.lua name net_<dataset>_... and its stored "
                        "options; required for a file that identifies none)")
    c.add_argument("--force", action="store_true", help="overwrite OUT if it exists")
    c.set_defaults(func=cmd_convert_weights)

    m = sub.add_parser("models", parents=parents, help="list the shipped networks",
                       description="List the networks shipped with mccnn_cl (names usable as --weights).")
    m.set_defaults(func=cmd_models)


def describe(weights) -> list:
    """Lines saying what a Weights holds."""
    conv = weights.conv_layers()
    same = all(c == conv[0] for c in conv)
    conv_txt = (f"{len(conv)} x {conv[0][0]} maps {conv[0][1]}x{conv[0][1]}" if same
                else ", ".join(f"{m} maps {k}x{k}" for m, k in conv))
    fc = weights.fc_layers()
    lines = [f"architecture: {weights.architecture}",
             f"conv layers:  {conv_txt} (ReLU {'after each' if weights.relu_after_last_conv else 'between them'})",
             f"fc layers:    {fc if fc else 'none (cost = -cosine of the features)'}",
             f"input:        {weights.input_channels} channel(s), {weights.patch_size}x{weights.patch_size} patches",
             f"parameters:   {weights.num_parameters():,}"]
    return lines


def cmd_convert_weights(args):
    from ..importers import convert

    out = args.output
    if not out.lower().endswith(".npz"):
        raise InputError(f"-o {out}: the output must be a .npz file")
    if os.path.isdir(out):
        raise InputError(f"-o {out} is a folder; name the .npz file to write")
    if os.path.exists(out) and not args.force:
        raise InputError(f"{out} exists (use --force to overwrite)")
    weights = convert(args.input, dataset=args.dataset)
    meta = weights.meta
    print(f"read:         {os.path.basename(args.input)} ({meta['source']['what']})")
    for line in describe(weights):
        print(line)
    stereo = weights.stereo
    keys = ", ".join(f"{k}={stereo[k]:g}" for k in KEY_SETTINGS if k in stereo)
    print(f"settings:     dataset {meta['dataset']} (the authors' released code): {keys}, ...")
    print(f"dataset from: {meta['dataset_source']}")
    print(f"trained by:   {meta['training']['by']}")
    print(f"licence:      {meta['licence']}")
    weights.save(out)
    print(f"wrote:        {out}")
    return 0


def cmd_models(args):
    from ..weights import Weights, shipped_models

    models = shipped_models()
    if not models:
        print("no shipped models are installed")
        return 0
    for name, path in models.items():
        w = Weights.load(path)
        size = os.path.getsize(path)
        print(f"{name}: {w.architecture}, {w.num_parameters():,} parameters, {size / 2**20:.1f} MiB")
        print(f"    {_summary(w.meta)}")
    return 0


def _summary(meta) -> str:
    """One line from a weights file's metadata: its source or training."""
    src = meta.get("source")
    if isinstance(src, dict) and src.get("what"):
        return str(src["what"])
    if isinstance(src, str) and src:
        return src
    training = meta.get("training")
    if isinstance(training, dict) and isinstance(training.get("trained_on"), dict):
        pairs = training["trained_on"]
        kinds = sorted({str(k).split("/")[0] for k in pairs})
        held_out = training.get("held_out") or []
        held = [k for k in held_out if k not in pairs]
        seen = [k for k in held_out if k in pairs]
        text = f"trained with mccnn_cl on {len(pairs)} pairs ({', '.join(kinds)})"
        if held:
            text += f", held out {', '.join(map(str, held))}"
        if seen:  # held out of the last run, but trained on earlier in the lineage (its --init)
            text += f" (the run also held out {', '.join(map(str, seen))}, which its starting weights had seen)"
        if training.get("finished_utc"):
            text += f"; finished {training['finished_utc']}"
        return text
    if isinstance(training, dict):
        for k in ("note", "data", "command"):
            if training.get(k):
                return f"trained: {str(training[k])[:160]}"
    if isinstance(training, str) and training:
        return f"trained: {training[:160]}"
    return "no description in its metadata"
