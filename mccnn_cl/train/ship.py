"""Turn a training run's exported weights into a shippable network file.

Run as ``python -m mccnn_cl.train.ship RUN/weights.npz -o mccnn_cl/models/NAME.npz
--name NAME --settings ARCH/DATASET --description TEXT``.

A run exports its weights with their provenance (``meta["training"]``); a
shipped file adds what a user of ``--weights NAME`` needs: a name, a one-line
description, the licence, and the stereo settings the network is run with
(``meta["stereo"]``, applied by :class:`~mccnn_cl.pipeline.StereoMatcher`
before the caller's own) with where they come from (``meta["stereo_source"]``).
The settings are one of the released code's tables
(:func:`mccnn_cl.settings.authors_settings`), named ``architecture/dataset``
(``mccnn-acrt/kitti2015``), or ``paper`` for the CVPR paper's KITTI values
(the :class:`~mccnn_cl.pipeline.Hyperparameters` defaults: no overrides),
and ``--set NAME=VALUE`` changes single settings of that table (recorded in
``stereo_source``).  The weights themselves are copied unchanged.
"""

from __future__ import annotations

import argparse
import sys

from mccnn_cl.errors import InputError
from mccnn_cl.hyperparameters import check_settings, parse_settings
from mccnn_cl.settings import AUTHORS, authors_settings
from mccnn_cl.models import resolve
from mccnn_cl.weights import Weights

#: The data licences of the shared data's datasets (its README), in the order a licence line names them.
DATA_LICENCES = (("kitti", "KITTI (CC BY-NC-SA 3.0)"),
                 ("middlebury", "Middlebury 2001-2014 (research use)"),
                 ("middeval3", "MiddEval3 (research use)"),
                 ("eth3d", "ETH3D (CC BY-NC-SA 4.0)"))


#: how this project's own licence lines begin (:func:`licence_for`)
OWN = "BSD-3-Clause (mccnn_cl)"


def start_licences(training) -> list:
    """``[(licence, what)]`` of the weights a run started from, along its lineage: ``init``
    (:func:`.train.record_init`) and ``source_training`` (:mod:`.selftrain`), each with the
    start's own; this project's own lines are left out (their pairs are in ``trained_on``)."""
    out, seen = [], set()

    def walk(t, depth=0):
        if not isinstance(t, dict) or depth > 50:
            return
        for key in ("init", "source_training"):
            sub = t.get(key)
            if not isinstance(sub, dict):
                continue
            lic = sub.get("licence")
            if isinstance(lic, str) and lic and not lic.startswith(OWN) and lic not in seen:
                seen.add(lic)
                src = sub.get("source") if isinstance(sub.get("source"), dict) else {}
                what = src.get("file") or sub.get("weights") or sub.get("name") or "the starting weights"
                out.append((lic, str(what)))
            walk(sub, depth + 1)

    walk(training)
    return out


def licence_for(meta: dict) -> str:
    """The licence line of weights trained on the pairs ``meta["training"]`` lists (the run's and,
    for a fine-tuned run, its start's): the code's licence and each dataset's, then the licence of
    any weights it started from that are not this project's (a converted network's: CNES's
    Apache-2.0, the authors' BSD-2-Clause).  A start of unknown licence (a converted file that is
    not one of the published networks) is an error: give the licence yourself."""
    from mccnn_cl.evaluation.datasets import dataset_of
    from mccnn_cl.evaluation.scoring import training_pairs

    from .selftrain import PSEUDO_KIND

    training = meta.get("training") if isinstance(meta.get("training"), dict) else {}
    trained, _ = training_pairs(meta)
    starts = start_licences(training)
    if not trained and not starts:
        raise InputError("the weights list no training pairs (meta['training']['trained_on']): "
                         "give --licence")
    unknown = [what for lic, what in starts if lic.lower().startswith("unknown")]
    if unknown:
        raise InputError(f"the licence of the weights this network started from ({', '.join(unknown)}) is unknown "
                         "(not one of the published networks): give --licence")
    own = {k for k in trained or () if str(k).split("/")[0] == PSEUDO_KIND}
    found = {dataset_of(k) for k in (trained or ()) if k not in own}
    names = [text for ds, text in DATA_LICENCES if ds in found]
    if own:
        names.append("the user's own images (pseudo-labels, mccnn-cl adapt)")
    line = OWN
    if names:
        body = names[0] if len(names) == 1 else ", ".join(names[:-1]) + " and " + names[-1]
        line += f"; trained on {body} images" if not own else f"; trained on {body}"
    for lic, what in starts:
        line += f"; fine-tuned from {what}, under its licence: {lic}"
    return line


def settings_table(spec: str) -> tuple[dict, str]:
    """``(overrides, source sentence)`` for ``paper`` or ``architecture/dataset``."""
    if spec == "paper":
        return {}, "the CVPR paper's KITTI stereo settings (the Hyperparameters defaults)"
    arch, _, dataset = spec.partition("/")
    if (arch, dataset) not in AUTHORS:
        known = ", ".join(["paper"] + [f"{a}/{d}" for a, d in AUTHORS])
        raise InputError(f"unknown settings {spec!r} (known: {known})")
    return authors_settings(arch, dataset), (f"the released code's {dataset} settings for {arch} "
                                             "(jzbontar/mc-cnn main.lua)")


def ship(src, out, name: str, settings: str, description: str, licence: str | None = None,
         settings_note: str | None = None, init=None, overrides: dict | None = None) -> Weights:
    """Read ``src``, add the shipping metadata, write ``out``; returns the Weights.

    ``overrides``: single settings that replace the table's (names and values
    checked as a matcher checks them).

    ``licence``: None: :func:`licence_for` the pairs the weights were trained on.

    ``init``: the weights (name or path) the run started from (its ``--init``),
    for a run whose provenance does not record them yet (:func:`.train.record_init`).
    """
    w = Weights.load(src)
    if "training" not in w.meta:
        raise InputError(f"{src}: no meta['training'] (not a file exported by a training run of this project)")
    if init is not None:
        if "init" in w.meta["training"]:
            raise InputError(f"{src}: its provenance already names the weights it started from")
        from .train import record_init

        record_init(w.meta["training"], resolve(init), init)
    stereo, source = settings_table(settings)
    if overrides:
        stereo = dict(stereo, **overrides)
        try:
            check_settings(overrides=stereo)
        except TypeError as exc:
            raise InputError(str(exc)) from exc
        source += " with these changed here: " + ", ".join(f"{k}={v}" for k, v in overrides.items())
    elif settings != "paper":
        source += ", used here unchanged"
    if licence is None:
        licence = licence_for(w.meta)
    w.meta.update(name=name, description=description, licence=licence, stereo=stereo,
                  stereo_source=source + (f"; {settings_note}" if settings_note else ""))
    w.save(out)
    return w


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m mccnn_cl.train.ship", description=__doc__.split("\n\n")[0])
    p.add_argument("weights", help="a run's exported weights (.npz)")
    p.add_argument("-o", "--out", required=True, help="the file to write (e.g. mccnn_cl/models/NAME.npz)")
    p.add_argument("--name", required=True)
    p.add_argument("--settings", required=True, help="paper, or ARCH/DATASET of mccnn_cl.settings (mccnn-acrt/kitti2015)")
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", dest="overrides",
                   help="change one setting of the --settings table (repeatable)")
    p.add_argument("--description", required=True)
    p.add_argument("--settings-note", default=None, help="why these settings (appended to stereo_source)")
    p.add_argument("--licence", default=None,
                   help="default: the code's licence and that of each dataset the weights were trained on")
    p.add_argument("--init", default=None, metavar="WEIGHTS",
                   help="the weights the run started from (its --init), if its provenance lacks them")
    args = p.parse_args(argv)
    try:
        ship(args.weights, args.out, args.name, args.settings, args.description, args.licence, args.settings_note,
             args.init, parse_settings(args.overrides))
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    from ..cli import run_entry_point  # a reader of stdout gone: exit 141, quietly

    raise SystemExit(run_entry_point(main))
