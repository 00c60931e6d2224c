"""Batches of stereo pairs for ``mccnn-cl match``: pairing by name, pair
outputs that are complete or absent, ``--resume``, per-pair failures and a
summary.  One process runs them here (:func:`run_batch`); with ``--workers`` or
``--scheduler`` a Dask cluster does (:mod:`mccnn_cl.distributed`), with the
same jobs, the same per-pair computation and the same writer.

Pairing (:func:`pair_globs`, :func:`pair_folders`): a left and a right image
are a pair when the text the wildcards of their globs matched is the same (in
each path component the text of its wildcards, ``*``, ``?`` and ``[...]``
alike, concatenated; components joined with "/"): ``image_2/*.png`` and
``image_3/*.png`` pair equal file names (KITTI); ``trainingQ/*/im0.png`` and
``trainingQ/*/im1.png`` pair the images of one folder (Middlebury, ETH3D);
``cam/L*.png`` (or ``cam/L????.png``) and ``cam/R*.png`` pair ``L0001`` with
``R0001``.  A folder given instead of a glob stands for its images, keyed
by file name without the extension; a file named without wildcards on both
sides is one pair.  ``--pairs-dir DIR`` pairs ``im0.*`` with
``im1.*`` in every folder at or under DIR.  Images without a partner are listed
and the batch is refused before any work (:class:`InputError`, exit 2).

A pair's outputs (:class:`Job`): the side files (colour picture, confidence,
labels, depth, point cloud) and the disparity map, each written to a
temporary name renamed when complete.  A write first removes the pair's old
disparity map and settings record (``--force``, or a pair ``--resume``
redoes), then writes its settings record (:func:`batch_settings`, a hidden
``.<map name>.mccnn.json`` beside the map), the side files, and the disparity
map last; so a pair whose every output exists is complete and was made in
one write, and one with only some is redone whole (``--resume`` skips
complete pairs).  A process killed at any point of a write leaves the pair
without its disparity map: incomplete.  ``--resume`` compares each complete
pair's record with this run's settings and refuses, before any work, when
some were made with other settings (or have no record) -- naming them and
the settings that differ.  A failure or an interrupt while a pair is written
removes the side files that write made, and an interrupted run leaves
complete pairs only (a process killed outright can leave side files, which
``--resume`` rewrites).  No output may be an input image of the batch, even
with ``--force`` or ``--resume``.

A full disk (ENOSPC), a read-only file system (EROFS) or an exhausted quota
(EDQUOT) stops the whole batch at the first pair it hits, naming the file or
folder (:class:`BatchStopped`, exit status 1): every later pair would fail the
same way.  Progress: a tqdm bar on a terminal, else a line ``matching: k/N
pairs, ... ETA ...`` on stderr every tenth of the batch and at least every
30 s (:class:`Progress`).
"""

from __future__ import annotations

import errno
import glob
import hashlib
import json
import math
import os
import re
import sys
import tempfile
import time
from dataclasses import dataclass, field

import numpy as np

from .errors import InputError, MccnnError

#: left / right file stems of the im0/im1 layout (Middlebury, ETH3D)
FOLDER_PAIR = ("im0", "im1")

#: end of a pair's settings record, ``.<map name>.mccnn.json`` (:attr:`Job.record`)
RECORD_SUFFIX = ".mccnn.json"

#: errors of the file system that every later pair would meet too: they stop a batch
STORAGE_ERRNOS = {errno.ENOSPC: "free some space", errno.EROFS: "write to a writable folder",
                  errno.EDQUOT: "free some of your quota"}


class BatchStopped(MccnnError):
    """A batch stopped at its first pair that met a full disk, a read-only file
    system or an exhausted quota (:data:`STORAGE_ERRNOS`)."""


@dataclass
class Job:
    """One pair of a batch: ``name`` (its key), images, the disparity file
    ``out`` (written last) and the side files written before it."""

    name: str
    left: str
    right: str
    out: str
    sides: list = field(default_factory=list)

    @property
    def outputs(self) -> list:
        return [*self.sides, self.out]

    @property
    def record(self) -> str:
        """The pair's settings record (:func:`batch_settings`): a hidden
        ``.<map name>.mccnn.json`` beside the disparity map, written before it."""
        d, name = os.path.split(self.out)
        return os.path.join(d, f".{name}{RECORD_SUFFIX}")

    def complete(self) -> bool:
        return all(os.path.isfile(p) for p in self.outputs)

    def started(self) -> bool:
        return any(os.path.exists(p) for p in self.outputs)

    def state(self) -> dict:
        """Each output's identity on disk (None: absent), taken before a write so
        that :meth:`remove_partial` knows which files that write made."""
        return {p: _file_identity(p) for p in [*self.outputs, self.record]}

    def remove_partial(self, before=None) -> None:
        """After a failed or interrupted write: unless the disparity map was
        written (then the pair is complete), delete the side files (and the
        settings record) this write made -- those whose identity differs from
        ``before`` (:meth:`state` before the write; None: every side file,
        unless a disparity map exists).  Side files of an earlier run that were
        not rewritten stay; the write removed the old disparity map first
        (:func:`write_pair`), so the pair is incomplete and ``--resume`` redoes it."""
        if before is None:
            if os.path.exists(self.out):
                return
            before = {}
        if os.path.exists(self.out) and _file_identity(self.out) != before.get(self.out):
            return  # written by this attempt: the pair is complete
        for p in [*self.sides, self.record]:
            if os.path.isfile(p) and _file_identity(p) != before.get(p):
                os.unlink(p)


def _file_identity(path):
    """(device, inode, size, mtime) of ``path``, None when absent: every output is
    written to a temporary file and renamed, so a rewritten file differs."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns


@dataclass
class Outputs:
    """The output options :func:`write_pair` reads (the CLI passes its parsed
    arguments): ``color``/``confidence``/``labels`` "" for the default file
    next to the disparity map, None for none; ``calib`` a calibration file
    (depth and point cloud; pass the parsed calibration to write_pair too)."""

    color: str | None = None
    confidence: str | None = None
    labels: str | None = None
    calib: str | None = None
    ply_ascii: bool = False


@dataclass
class PairResult:
    """What matching one pair gives (computed by a worker or by this process)."""

    disparity: np.ndarray
    max_disp: int
    seconds: float
    confidence: np.ndarray | None = None
    labels: np.ndarray | None = None
    where: str = ""
    min_disp: int = 0
    auto: dict | None = None  # the automatic range's report (--disp-range auto)


@dataclass
class Summary:
    done: list = field(default_factory=list)
    skipped: list = field(default_factory=list)
    failed: list = field(default_factory=list)   # (name, reason, is_input_error)

    def report(self, out=None) -> None:
        out = out or sys.stdout
        print(f"done {len(self.done)}, skipped {len(self.skipped)} (outputs complete), "
              f"failed {len(self.failed)}", file=out, flush=True)
        for name, reason, _ in self.failed:
            print(f"  failed {name}: {reason}", file=out, flush=True)

    def exit_status(self) -> int:
        """0 when nothing failed; 2 when every failure is bad input (unreadable
        image, sizes differ ...); 1 otherwise."""
        if not self.failed:
            return 0
        return 2 if all(bad_input for _, _, bad_input in self.failed) else 1


# -- pairing -----------------------------------------------------------------

def _image_files(spec, what, image_extensions):
    """(files, keys): a folder's images keyed by stem, or a glob's matches keyed
    by the text its wildcards matched (:func:`_wildcard_key`; a glob without
    wildcards: the file's stem)."""
    if os.path.isdir(spec):
        files = sorted(os.path.join(spec, f) for f in os.listdir(spec)
                       if f.lower().endswith(image_extensions) and os.path.isfile(os.path.join(spec, f)))
        keys = [os.path.splitext(os.path.basename(f))[0] for f in files]
    else:
        files = sorted(f for f in glob.glob(spec) if os.path.isfile(f))
        pattern, components = _wildcard_regex(spec)
        keys = []
        for f in files:
            m = pattern.fullmatch(f)
            if m is None or not m.groups():
                key = os.path.splitext(os.path.basename(f))[0]
            else:
                key = _wildcard_key(m, components)
            keys.append(_strip_extension(key, image_extensions))
    if not files:
        raise InputError(f"no {what} images match {spec!r}")
    return files, keys


def _wildcard_key(match, components):
    """A glob match's key: in each path component that holds wildcards, the
    text they matched, concatenated; the components joined with "/"
    (``cam/L????.png`` on ``cam/L0001.png``: ``0001``; ``*/im0.png`` on
    ``Adirondack/im0.png``: ``Adirondack``)."""
    parts = {}
    for group, component in enumerate(components, start=1):
        parts.setdefault(component, []).append(match.group(group))
    return "/".join("".join(parts[c]) for c in sorted(parts))


def _is_wildcard_free(spec):
    """A ``-l``/``-r`` value that names one file (no folder, no wildcard)."""
    return not os.path.isdir(spec) and not _wildcard_regex(spec)[1]


def _strip_extension(key, image_extensions):
    return key[:-len(os.path.splitext(key)[1])] if key.lower().endswith(image_extensions) else key


def _wildcard_regex(pattern):
    """(regex, components): a regex matching what (non-recursive) ``glob``
    matches for ``pattern``, one group per wildcard (``*``, ``?``, ``[...]``),
    and for each group the index of the path component it lies in."""
    out, components, i, component = [], [], 0, 0
    seps = "/" if os.sep == "/" else "/" + os.sep
    not_sep = "[^/]" if os.sep == "/" else r"[^/\\]"
    while i < len(pattern):
        c = pattern[i]
        if c in seps:
            component += 1
        if c == "*":
            j = i
            while j < len(pattern) and pattern[j] == "*":
                j += 1
            out.append(f"({not_sep}*)")  # glob without recursive=True: ** is * (one component)
            components.append(component)
            i = j
            continue
        if c == "?":
            out.append(f"({not_sep})")
            components.append(component)
        elif c == "[":
            j = pattern.find("]", i + 2)
            if j < 0:
                out.append(re.escape(c))
            else:
                body = pattern[i + 1:j]
                if body.startswith("!"):
                    body = "^" + body[1:]
                out.append("([" + body.replace("\\", "\\\\") + "])")
                components.append(component)
                i = j + 1
                continue
        else:
            out.append(re.escape(c))
        i += 1
    return re.compile("".join(out)), components


def _unpartnered(lefts_only, rights_only, how):
    def names(items, n=8):
        items = sorted(items)
        text = ", ".join(items[:n])
        return text + (f" ... and {len(items) - n} more" if len(items) > n else "")
    parts = []
    if lefts_only:
        parts.append(f"{len(lefts_only)} left image(s) without a right partner: {names(lefts_only)}")
    if rights_only:
        parts.append(f"{len(rights_only)} right image(s) without a left partner: {names(rights_only)}")
    return InputError("; ".join(parts) + f" (pairs are matched by {how}; nothing was matched)")


def _pair_keys(lefts, lkeys, rights, rkeys, how):
    for files, keys, side in ((lefts, lkeys, "left"), (rights, rkeys, "right")):
        seen = {}
        for f, k in zip(files, keys):
            if k in seen:
                raise InputError(f"{seen[k]} and {f} are both {side} images of pair {k!r} ({how})")
            seen[k] = f
    lmap, rmap = dict(zip(lkeys, lefts)), dict(zip(rkeys, rights))
    lonly = [lmap[k] for k in lmap if k not in rmap]
    ronly = [rmap[k] for k in rmap if k not in lmap]
    if lonly or ronly:
        raise _unpartnered(lonly, ronly, how)
    return [(k, lmap[k], rmap[k]) for k in sorted(lmap)]


def pair_globs(left_spec, right_spec, image_extensions):
    """``[(name, left, right)]`` for ``--left-glob``/``--right-glob`` (module docstring);
    ``name``: the left image's file name without extension when those differ,
    else the pair's key (``Adirondack`` for ``trainingQ/*/im0.png``)."""
    lefts, lkeys = _image_files(left_spec, "left", image_extensions)
    rights, rkeys = _image_files(right_spec, "right", image_extensions)
    if _is_wildcard_free(left_spec) and _is_wildcard_free(right_spec):  # one file each side: one pair
        return [(os.path.splitext(os.path.basename(lefts[0]))[0], lefts[0], rights[0])]
    pairs = _pair_keys(lefts, lkeys, rights, rkeys, "the text the globs' wildcards match (file name, or folder)")
    stems = [os.path.splitext(os.path.basename(lp))[0] for _, lp, _ in pairs]
    if len(set(stems)) == len(stems):  # outputs named after the left images when their names differ
        pairs = [(stem, lp, rp) for stem, (_, lp, rp) in zip(stems, pairs)]
    return pairs


def pair_folders(root, image_extensions):
    """``[(key, left, right)]``: ``im0.*`` and ``im1.*`` of each folder at or under ``root``."""
    if not os.path.isdir(root):
        raise InputError(f"--pairs-dir {root}: not a folder")
    lefts, lkeys, rights, rkeys = [], [], [], []
    base = os.path.basename(os.path.normpath(os.path.abspath(root)))
    for folder, dirs, files in os.walk(root):
        dirs.sort()
        rel = os.path.relpath(folder, root)
        key = base if rel == "." else rel.replace(os.sep, "/")
        for f in sorted(files):
            stem, ext = os.path.splitext(f)
            if ext.lower() not in image_extensions:
                continue
            if stem == FOLDER_PAIR[0]:
                lefts.append(os.path.join(folder, f))
                lkeys.append(key)
            elif stem == FOLDER_PAIR[1]:
                rights.append(os.path.join(folder, f))
                rkeys.append(key)
    if not lefts and not rights:
        raise InputError(f"no folder under {root} holds {FOLDER_PAIR[0]}/{FOLDER_PAIR[1]} images")
    return _pair_keys(lefts, lkeys, rights, rkeys, f"folder ({FOLDER_PAIR[0]}.* with {FOLDER_PAIR[1]}.*)")


def output_name(key) -> str:
    """A pair's key as a file name stem (folders joined with '_')."""
    name = re.sub(r"[/\\]+", "_", key).strip("_")
    return name or "pair"


# -- jobs --------------------------------------------------------------------

def make_jobs(args, calib=None):
    """The batch's :class:`Job` list from ``args`` (pairing, output names, checks:
    a ``.png`` format refuses a stated range it cannot hold, :func:`check_png_range`);
    nothing is read or written."""
    from .cli.common import DISPARITY_FORMATS, IMAGE_EXTENSIONS, _confidence_outputs, _side_outputs
    if args.pairs_dir is not None:
        if args.left_glob is not None or args.right_glob is not None:
            raise InputError("give either --pairs-dir DIR or -l LEFT_GLOB -r RIGHT_GLOB, not both")
        pairs = pair_folders(args.pairs_dir, IMAGE_EXTENSIONS)
    else:
        pairs = pair_globs(args.left_glob, args.right_glob, IMAGE_EXTENSIONS)
    ext = "." + args.format
    if ext not in DISPARITY_FORMATS:
        raise InputError(f"--format must be one of {', '.join(DISPARITY_FORMATS)}")
    jobs, names = [], {}
    for key, lp, rp in pairs:
        name = output_name(key)
        if name in names:
            raise InputError(f"pairs {names[name]!r} and {key!r} would both write {name}{ext}")
        names[name] = key
        out = os.path.join(args.output_dir, name + ext)
        check_png_range(out, args, calib)
        color, depth, ply = _side_outputs(out, args)
        sides = [p for p in (color, *_confidence_outputs(out, args), depth, ply) if p is not None]
        jobs.append(Job(name, lp, rp, out, sides))
    return jobs


def plan_outputs(jobs, args, settings=None):
    """Jobs to run, and the complete ones ``--resume`` skips; refused before any
    work: an output that is an input image of any pair (even with
    ``--force``/``--resume``), two outputs that are the same file, existing
    outputs without ``--resume``/``--force``, and with ``--resume`` and
    ``settings`` (:func:`batch_settings`) complete pairs whose record states
    other settings, or none (:func:`check_resume`)."""
    from .cli.common import _check_outputs
    if not os.path.isdir(args.output_dir):
        try:
            os.makedirs(args.output_dir, exist_ok=True)
        except OSError as exc:
            raise InputError(f"--output-dir {args.output_dir}: cannot create it ({exc.strerror or exc})") from exc
    inputs = [f for job in jobs for f in (job.left, job.right)]
    taken = {}  # real path -> output, across the batch
    for job in jobs:
        _check_outputs(job.outputs, args.resume or args.force, inputs, taken)
    todo, skipped = [], []
    for job in jobs:
        if args.resume and job.complete():
            skipped.append(job)
            continue
        todo.append(job)
    if args.resume and settings is not None:
        check_resume(skipped, settings, args.output_dir)
    return todo, skipped


# -- settings records ----------------------------------------------------------

def weights_digest(weights) -> str:
    """sha256 of a network: its architecture, every array (shape and bytes) and
    the stereo settings it carries -- what its disparity maps depend on."""
    h = hashlib.sha256(str(weights.architecture).encode())
    for w, b in [*weights.conv, *weights.fc]:
        for a in (w, b):
            a = np.ascontiguousarray(a)
            h.update(f"{a.dtype.str}{a.shape}".encode())
            h.update(a.tobytes())
    h.update(json.dumps(weights.stereo, sort_keys=True, default=str).encode())
    return h.hexdigest()


def batch_settings(args, calib=None, weights=None) -> dict:
    """What a batch's outputs depend on, as a JSON-able dict recorded with each
    pair (:func:`write_record`): cost, network (sha256 of its arrays and
    settings, and the name given), disparity range, volume storage, ``--set``
    values, and with depth the calibration (sha256) and point-cloud encoding.
    Not in it: the device, ``--memory-limit``, ``--workers`` (they do not
    choose the result) and which side files are written (a missing one makes
    the pair incomplete anyway)."""
    from .cli.common import _hyperparameters
    low, levels = batch_range(args, calib)
    out = {"cost": args.cost,
           "disparities": "auto" if levels == "auto" else f"{low}..{low + levels - 1}",
           "volume_dtype": getattr(args, "volume_dtype", "float32") or "float32",
           "set": json.loads(json.dumps(_hyperparameters(getattr(args, "hyper", []) or []),
                                        sort_keys=True, default=str))}
    if args.cost == "cnn" and weights is not None:
        out["weights"] = f"sha256 {weights_digest(weights)[:16]} ({getattr(args, 'weights', None) or 'shipped'})"
    if calib is not None and getattr(calib, "has_depth", False) and not getattr(args, "no_depth", False):
        from .importers import sha256
        out["calib"] = f"sha256 {sha256(args.calib)[:16]} ({os.path.basename(args.calib)})"
        out["ply"] = "ascii" if getattr(args, "ply_ascii", False) else "binary"
    return out


def _same_settings(a, b) -> bool:
    """Equal settings; a network or calibration counts by its sha256, not the name it was given by."""
    def norm(s):
        return {k: (v.split(" (")[0] if k in ("weights", "calib") and isinstance(v, str) else v)
                for k, v in s.items()}
    return norm(a) == norm(b)


def write_record(job, settings) -> None:
    """The pair's settings record (:attr:`Job.record`), atomically."""
    from .atomic import atomic_write
    from . import __version__
    text = json.dumps({"settings": settings, "written_by": f"mccnn-cl {__version__}"}, indent=1, sort_keys=True)

    def write(tmp):
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text + "\n")
    atomic_write(job.record, write)


def read_record(job):
    """The settings in the pair's record; None when it has none or it cannot be read."""
    try:
        with open(job.record, encoding="utf-8") as f:
            settings = json.load(f)["settings"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return settings if isinstance(settings, dict) else None


def check_resume(complete, settings, output_dir) -> None:
    """``--resume``: InputError before any work when complete pairs were made
    with other settings than ``settings`` (or have no record of theirs): it
    names them and what differs; the same settings, or ``--force``, go on."""
    other, unknown, diffs = [], [], {}
    for job in complete:
        rec = read_record(job)
        if rec is None:
            unknown.append(job.name)
        elif not _same_settings(rec, settings):
            other.append(job.name)
            for k in sorted(set(rec) | set(settings)):
                if rec.get(k) != settings.get(k) and not _same_settings({k: rec.get(k)}, {k: settings.get(k)}):
                    diffs.setdefault(k, (rec.get(k), settings.get(k)))
    if not other and not unknown:
        return

    def names(items, n=6):
        return ", ".join(items[:n]) + (f" ... and {len(items) - n} more" if len(items) > n else "")

    def show(v):
        return "none" if v is None else (json.dumps(v) if isinstance(v, dict) else str(v))
    parts = []
    if other:
        what = "; ".join(f"{k} {show(a)} there, {show(b)} now" for k, (a, b) in diffs.items())
        parts.append(f"{len(other)} complete pair(s) were made with other settings ({names(other)}: {what})")
    if unknown:
        parts.append(f"{len(unknown)} complete pair(s) have no record of their settings ({names(unknown)}; "
                     "written by an earlier mccnn-cl or without one)")
    raise InputError(f"--resume in {output_dir}: " + "; ".join(parts) + "; nothing was matched: rerun with the "
                     "settings they were made with, or pass --force instead of --resume to redo every pair "
                     "with these")


def check_png_range(out, args, calib=None) -> None:
    """A ``.png`` output and a stated range (not ``--disp-range auto``) it cannot
    hold (a negative minimum, or past 255.996 px): refused before any work, as
    for one pair (:func:`mccnn_cl.cli.common._check_png_range`)."""
    from .cli.common import _check_png_range
    low, levels = batch_range(args, calib)
    if levels != "auto":
        _check_png_range(out, levels, low)


# -- one pair -----------------------------------------------------------------

def batch_range(args, calib):
    """The range every pair of the batch searches, from one parse of the
    options: ``(M, D)`` (``--min-disp``/``--max-disp`` or ``--disp-range
    MIN:MAX``; D by default the calibration's ndisp, else 228), or ``(0,
    "auto")`` (``--disp-range auto``: each pair gets its own range from the
    coarse passes, :func:`mccnn_cl.disprange.choose_range`)."""
    from .cli.common import _range_request
    request = _range_request(args)
    if request == "auto":
        return 0, "auto"
    low, levels = request
    if levels is None:
        levels = calib.ndisp if (calib is not None and calib.ndisp) else 228
    return int(low or 0), int(levels)


def compute_pair(job, matcher_for, max_disp, want_confidence) -> PairResult:
    """Read and match one pair; ``matcher_for(max_disp)`` gives the (kept)
    matcher, ``max_disp`` D or ``"auto"`` (the pair's own range, chosen here;
    the result's ``min_disp``/``max_disp`` are that range and ``auto`` what the
    coarse passes found)."""
    from .cli.common import _auto_output_range, _gray
    from .io import read_image
    from .validate import check_pair, patch_size
    left_img, right_img = read_image(job.left), read_image(job.right)
    matcher = matcher_for(max_disp)
    names, patch = (job.left, job.right), patch_size(matcher.weights)
    auto = rng = None
    if max_disp == "auto":
        check_pair(left_img, right_img, 1, patch, names)
    else:
        check_pair(left_img, right_img, max_disp, patch, names, min_disparity=matcher.min_disparity)
    t0 = time.perf_counter()
    gray_l, gray_r = _gray(left_img), _gray(right_img)
    if max_disp == "auto":
        auto = matcher.choose_range(gray_l, gray_r)
        rng = _auto_output_range(job.out, auto)
        lo, levels = rng[0], rng[1] - rng[0] + 1
    else:
        lo, levels = matcher.min_disparity, max_disp
    res = matcher.compute(gray_l, gray_r, confidence=want_confidence, disparity_range=rng)
    seconds = time.perf_counter() - t0
    if want_confidence:
        return PairResult(res.disparity, levels, seconds, res.confidence, res.labels, min_disp=lo, auto=auto)
    return PairResult(res, levels, seconds, min_disp=lo, auto=auto)


def done_line(job, result) -> str:
    """The line said for a matched pair: size, range (with the automatic range's
    report), valid fraction, seconds."""
    from .cli.common import _range_text
    lo, hi = result.min_disp, result.min_disp + result.max_disp - 1
    if lo == 0 and result.auto is None:
        levels = f"{result.max_disp} disparities"
    else:
        levels = _range_text(lo, hi, result.auto)
    fin = np.isfinite(result.disparity)
    return (f"{job.out}: {result.disparity.shape[1]}x{result.disparity.shape[0]}, {levels}, "
            f"{fin.mean():.1%} valid, {result.seconds:.2f} s")


def write_pair(job, result, args, calib, settings=None) -> None:
    """Every output of ``job``: the old disparity map and settings record
    removed first (so a write killed at any point leaves the pair incomplete),
    then the record of ``settings`` (:func:`batch_settings`; none when None),
    the side files, and the disparity map last (each atomic); on any failure
    or interrupt the side files this write made are removed."""
    from .cli.common import _check_calib_size, _save_confidence, _save_outputs
    from .io import read_image
    before = job.state()
    try:
        for p in (job.out, job.record):  # a rewrite (--force, or a pair --resume redoes)
            if os.path.isfile(p):
                os.unlink(p)
        if settings is not None:
            write_record(job, settings)
        left_img = read_image(job.left) if calib is not None else None  # point-cloud colours
        said = vars(args).setdefault("_calib_sizes_said", set())  # once per image size and run, not per pair
        if left_img is not None and left_img.shape[:2] not in said:
            said.add(left_img.shape[:2])
            _check_calib_size(calib, left_img, job.left, args.calib)
        if result.confidence is not None:
            _save_confidence(job.out, result, args)
        lo = result.min_disp
        _save_outputs(job.out, result.disparity, left_img, args, calib, (lo, lo + result.max_disp - 1))
    except BaseException:
        job.remove_partial(before)
        raise


def describe_failure(exc) -> tuple:
    """(one-line reason, is bad input) for a pair that failed."""
    text = str(exc).strip().splitlines()
    msg = text[0] if text else type(exc).__name__
    if isinstance(exc, InputError):
        return msg, True
    if isinstance(exc, MccnnError):
        return msg, False
    return f"{type(exc).__name__}: {msg}", False


def _storage_error(exc):
    """The OSError of :data:`STORAGE_ERRNOS` in ``exc`` or what caused it, else None."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if isinstance(exc, OSError) and exc.errno in STORAGE_ERRNOS:
            return exc
        exc = exc.__cause__ or exc.__context__
    return None


def _probe_folder(folder, nbytes=65536):
    """The OSError of :data:`STORAGE_ERRNOS` that writing ``nbytes`` into
    ``folder`` meets (a full disk, a read-only file system, a quota), else
    None: asked after a write that failed without saying why (cv2 only
    returns False).  ``nbytes``: at least what the failed file needed (the
    write's own temporary file is gone by now, so a small probe could fit)."""
    from .atomic import temp_prefix
    try:
        fd, tmp = tempfile.mkstemp(prefix=temp_prefix(), dir=folder)  # atomic's name: removed if we are killed
    except OSError as exc:
        return exc if exc.errno in STORAGE_ERRNOS else None
    try:
        block, left = b"\0" * min(int(nbytes), 1 << 20), int(nbytes)
        while left > 0:
            left -= os.write(fd, block[:left])
        os.fsync(fd)
    except OSError as exc:
        return exc if exc.errno in STORAGE_ERRNOS else None
    finally:
        os.close(fd)
        try:
            os.unlink(tmp)
        except OSError:
            pass
    return None


def storage_stop(exc, job, folder, writing=True, left=None, probe_bytes=65536):
    """A :class:`BatchStopped` when ``exc`` (the failure of ``job``) is a full
    disk, a read-only file system or an exhausted quota -- every later pair
    would fail the same way -- naming the file (or ``folder``); None for a
    failure of this pair only.  ``writing``: the failure came from writing
    its outputs into ``folder`` (a failure that gives no reason is then
    checked by writing ``probe_bytes``, :func:`_probe_folder`: give at least
    the largest output's size, e.g. the float32 map's bytes); ``left``:
    pairs left, said in the message."""
    from .atomic import PREFIX
    err = _storage_error(exc)
    if err is None and writing:
        err = _probe_folder(folder, probe_bytes)
    if err is None:
        return None
    name = os.fsdecode(err.filename) if err.filename is not None else None
    if name is not None and os.path.basename(name).startswith(PREFIX):
        name = os.path.dirname(name) or "."  # a temporary file: its folder
    if name is None and writing:
        name = folder
    where = f"{name}: " if name else ""
    doing = f"writing pair {job.name}" if writing else f"matching pair {job.name}"
    rest = f" with {left} pair(s) left" if left else ""
    return BatchStopped(f"{where}{os.strerror(err.errno)} ({doing}): the batch stops here{rest}, as every "
                        f"later pair would fail too; {STORAGE_ERRNOS[err.errno]} and run it again with --resume")


def _probe_size(result) -> int:
    """Bytes a probe write after a failed write of ``result``'s files needs: more
    than any one of them (the float32 map's size and 64 KiB: a 16-bit PNG, an
    8-bit colour picture with its legend, a PFM)."""
    return (result.disparity.nbytes if result is not None else 0) + 65536


class Progress:
    """Progress of a batch: a tqdm bar on a terminal; elsewhere (a log, a pipe)
    a line ``<desc>: k/N <unit>s, <elapsed> elapsed, ETA <left>`` on stderr,
    flushed, every tenth of the total and at least every ``every_s`` seconds
    (said when a pair ends), and at the end.  ``write`` prints a message
    (stdout) without breaking the bar."""

    def __init__(self, total, unit="pair", desc="matching", every_s=30.0, position=0, tty=None,
                 clock=time.monotonic):
        from .cli.common import _tty
        self.total, self.unit, self.desc, self.every_s, self.clock = int(total), unit, desc, every_s, clock
        self.n = 0
        self.tty = _tty() if tty is None else tty
        self.bar = None
        if self.tty:
            from tqdm import tqdm
            self.bar = tqdm(total=self.total, unit=unit, desc=desc, position=position)
        self.step = max(1, math.ceil(self.total / 10))
        self.start = self.last = clock()

    def update(self, n=1) -> None:
        if self.bar is not None:
            self.bar.update(n)
            return
        before, self.n = self.n, self.n + n
        now = self.clock()
        if (self.n >= self.total or self.n // self.step > before // self.step
                or now - self.last >= self.every_s):
            self.last = now
            elapsed = now - self.start
            line = f"{self.desc}: {self.n}/{self.total} {self.unit}s, {_interval(elapsed)} elapsed"
            if self.n < self.total:
                line += f", ETA {_interval(elapsed / self.n * (self.total - self.n))}" if self.n else ""
            print(line, file=sys.stderr, flush=True)

    def write(self, msg) -> None:
        if self.bar is not None:
            self.bar.write(msg)
        else:
            print(msg, flush=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _interval(seconds) -> str:
    s = int(round(seconds))
    h, rest = divmod(s, 3600)
    return f"{h}:{rest // 60:02d}:{rest % 60:02d}" if h else f"{rest // 60:02d}:{rest % 60:02d}"


# -- the batch ------------------------------------------------------------------

def prepare(args):
    """Checks shared by the one-process and the Dask batch: (jobs to run,
    skipped, calib, weights, settings) -- settings the record of every pair
    written (:func:`batch_settings`), checked against the records of complete
    pairs with ``--resume``."""
    if args.output is not None:
        raise InputError("-o is for one pair; a batch writes into --output-dir")
    if args.output_dir is None:
        raise InputError("a batch needs --output-dir DIR")
    if os.path.exists(args.output_dir) and not os.path.isdir(args.output_dir):
        raise InputError(f"--output-dir {args.output_dir} is a file, not a folder")
    if args.color:
        raise InputError("in a batch, --color takes no file name (pictures go next to each output)")
    if args.confidence or args.labels:
        raise InputError("in a batch, --confidence and --labels take no file name (maps go next to each output)")
    if args.resume and args.force:
        raise InputError("--resume keeps complete outputs and --force overwrites them: give one")
    from .cli.common import _load_weights, _read_calibration
    calib = _read_calibration(args)
    jobs = make_jobs(args, calib)
    weights = _load_weights(args)  # a bad weights file fails here, before any work
    settings = batch_settings(args, calib, weights)
    todo, skipped = plan_outputs(jobs, args, settings)
    return todo, skipped, calib, weights, settings


def run_batch(args) -> int:
    """``mccnn-cl match`` on a batch in this process (no ``--workers``/``--scheduler``)."""
    from .cli.common import _make_matcher, _say
    todo, skipped, calib, weights, settings = prepare(args)
    summary = Summary(skipped=[j.name for j in skipped])
    want = args.confidence is not None or args.labels is not None
    low, levels = batch_range(args, calib)
    matchers, ctx = {}, None

    def matcher_for(max_disp):
        nonlocal ctx
        if max_disp not in matchers:
            from .opencl.context import ClContext
            if ctx is None:
                ctx = ClContext(args.device)
            matchers[max_disp] = _make_matcher(args, max_disp, weights, ctx=ctx, min_disparity=low)
        return matchers[max_disp]

    with Progress(len(todo)) as bar:
        for i, job in enumerate(todo):
            writing, result = False, None
            try:
                result = compute_pair(job, matcher_for, levels, want)
                writing = True
                write_pair(job, result, args, calib, settings)
            except (KeyboardInterrupt, SystemExit):
                raise
            except Exception as exc:  # noqa: BLE001 - reported per pair, the batch goes on
                stop = storage_stop(exc, job, args.output_dir, writing, left=len(todo) - i - 1,
                                    probe_bytes=_probe_size(result))
                reason, bad_input = describe_failure(exc)
                summary.failed.append((job.name, reason, bad_input))
                if stop is not None:  # a full disk, a read-only file system, a quota: no later pair can be written
                    bar.close()
                    summary.report()
                    raise stop from exc
                bar.write(f"{job.name}: failed: {reason}")
            else:
                summary.done.append(job.name)
                if args.verbose or result.auto is not None:  # an automatic range is always said
                    bar.write(done_line(job, result))
            bar.update(1)
    summary.report()
    if summary.done:
        _say(f"wrote {len(summary.done)} disparity maps to {args.output_dir}")
    return summary.exit_status()
