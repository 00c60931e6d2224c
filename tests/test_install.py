"""`pip install .` gives a package that carries its kernels and the demo pair (works outside the checkout)."""

import pytest
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_non_editable_install_carries_kernels(tmp_path):
    target = tmp_path / "site"
    r = subprocess.run(
        [sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation",
         "--target", str(target), str(REPO)],
        capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    kernels = sorted(p.name for p in (target / "mccnn_cl" / "kernels").iterdir())
    sources = sorted(p.name for p in (REPO / "mccnn_cl" / "kernels").iterdir() if p.suffix in (".cl", ".h"))
    assert sources and set(sources) <= set(kernels), (sources, kernels)
    for sub in ("stages", "reference", "train", "importers"):
        assert (target / "mccnn_cl" / sub / "__init__.py").exists(), sub
    demo = sorted(p.name for p in (REPO / "mccnn_cl" / "demo").iterdir())
    assert "disp0GT.png" in demo and demo == sorted(p.name for p in (target / "mccnn_cl" / "demo").iterdir())
    code = ("import mccnn_cl, mccnn_cl.opencl.context as c; ctx = c.ClContext(); "
            "assert mccnn_cl.__file__.startswith(%r), mccnn_cl.__file__; "
            "from mccnn_cl.cli.demo import demo_dir, load_demo_pair\n"
            "with demo_dir() as d: p = load_demo_pair(d)\n"
            "assert p.shape == (496, 718) and p.valid_noc.sum() > 300000, p.shape\n"
            "print(ctx.kernel_dir)" % str(target))
    r = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True,
                       env={"PYTHONPATH": str(target), "PATH": "/usr/bin:/bin"}, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.strip().startswith(str(target)), r.stdout
