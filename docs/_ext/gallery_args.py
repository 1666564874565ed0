"""sphinx-gallery hooks for examples/: the command line each example runs with, and a scraper
that shows the PNG files an example writes (the examples save their figures and close them, so
matplotlib's own scraper would find none).

Each example writes into ``docs/_build/gallery-out/<example>/`` (``--out``), at a size that keeps
the gallery to about a minute on 2 cores; the sizes are the ``ARGS`` below.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from sphinx_gallery.scrapers import figure_rst

OUT = Path(__file__).resolve().parents[1] / "_build" / "gallery-out"
ARGS = {
    "fig4_1d_recovery": [],
    "fig6_heatmaps": ["--quick"],
    "fig5_2d_superres": ["--methods", "bp,bpdn"],
    "dense_planar_omega_k": ["--stops", "40"],
    "turntable_own_data": ["--pings", "90", "--spacing", "0.006"],
}
_SHOWN: set[Path] = set()


def _out(src_file: str) -> Path:
    return OUT / Path(src_file).stem


def reset_argv(gallery_conf: dict, script_vars: dict) -> list[str]:
    """The arguments an example runs with: its output folder and its small size."""
    out = _out(script_vars["src_file"])
    out.mkdir(parents=True, exist_ok=True)
    return ["--out", str(out), *ARGS.get(Path(script_vars["src_file"]).stem, [])]


def png_scraper(block, block_vars: dict, gallery_conf: dict) -> str:
    """The rST showing the PNG files the example has written since the last block."""
    out = _out(block_vars["src_file"])
    new = sorted(p for p in out.glob("*.png") if p not in _SHOWN) if out.is_dir() else []
    paths = []
    for png, target in zip(new, block_vars["image_path_iterator"], strict=False):
        shutil.copyfile(png, target)
        _SHOWN.add(png)
        paths.append(target)
    return figure_rst(paths, gallery_conf["src_dir"])
