"""Sphinx extension: one page per stored benchmark result in bench/results/, and an index.

At ``config-inited`` every result (the files sharing a stem: ``.json``, ``.md``, ``.png``) becomes
``docs/benchmarks/<stem>.md``: a table of where it ran (device, date, host load, peer), then the
result's own Markdown report where there is one, else its JSON rendered as tables, and its plot
(for a result stored without one: its run times per method, drawn from the JSON here).
``docs/benchmarks/`` is generated (not in git); the guide links to these pages, so a figure is
stated once, beside its device, date and peer.
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "bench" / "results"
PEERS = {  # text in a result -> the peer it names (what clsas was compared with in the same run)
    r"numba peer|numba_peer": "Numba",
    r"c/openmp peer|c_openmp": "C/OpenMP",
    r"against cvxpy|bpdn_vs_cvxpy|bpdn_cvxpy": "cvxpy (reference solver)",
    r"\bmlk\b|known-count|ML \(known": "known-count maximum likelihood",
    r"\"bound\"|bound_success|bound with|cram[eé]r": "Cramér–Rao bound",
    r"numpy_twin|NumPy twin": "the NumPy twin",
    r"serial (sweep|grid|run)": "the serial run (Dask)",
    r"against exact backprojection|speed-up": "exact backprojection (bp)",
    r"fista alone": "FISTA alone (the solver before the Newton polish)",
    r"error-free": "the error-free scan",
}

MAX_ROWS = 80


def _find(data: Any, keys: tuple[str, ...]) -> Any:
    """The first value under one of ``keys`` at the top level or one level down."""
    if not isinstance(data, dict):
        return None
    for key in keys:
        if key in data:
            return data[key]
    for value in data.values():
        if isinstance(value, dict):
            for key in keys:
                if key in value:
                    return value[key]
    return None


def _device(data: Any, report: str) -> str:
    device = _find(data, ("device",))
    named = re.search(r"on (pthread-[^()|\n]*?Portable Computing Language|[^()|\n,]*?) \((opencl|numpy)\)", report)
    if not device and named:
        device = named.group(1)
    if isinstance(device, dict):
        device = device.get("name")
    if device:
        return str(device)
    cpu = _find(data, ("cpu", "machine"))
    cores = _find(data, ("cores", "cpus"))
    host = _find(data, ("host",))
    parts = [str(p) for p in (cpu, f"{cores} cores" if cores else None) if p]
    if parts:
        return ", ".join(parts) + (f" (host {host})" if isinstance(host, str) else "")
    return f"host '{host}' (device not recorded in the file)" if host else "not recorded in the file"


def _date(data: Any, stem: str) -> str:
    date = _find(data, ("date",))
    return str(date) if date else stem[:10]


def _load(data: Any) -> str:
    for keys in (("load_1min",), ("load_start", "load_at_start"), ("uptime_start",), ("load_before",)):
        value = _find(data, keys)
        if value is not None:
            if isinstance(value, float):
                return f"{value:.2f}"
            return str(value)
    return "not recorded"


def _peers(text: str) -> str:
    found = [name for pattern, name in PEERS.items() if re.search(pattern, text, re.IGNORECASE)]
    return ", ".join(dict.fromkeys(found)) or "none (a run of clsas alone)"


def _cell(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, (dict, list)):
        return "…"
    return str(value).replace("|", "\\|").replace("\n", " ")


def _tables(data: Any, title: str = "", depth: int = 0) -> list[str]:
    """A JSON result as Markdown: scalars in one table, each list of records in another."""
    out: list[str] = []
    if isinstance(data, dict):
        scalars = {k: v for k, v in data.items() if not isinstance(v, (dict, list))}
        if scalars:
            out += [f"\n{'#' * min(depth + 3, 6)} {title or 'Values'}\n" if depth else "", "| field | value |",
                    "|---|---|"]
            out += [f"| {k} | {_cell(v)} |" for k, v in scalars.items()]
        for key, value in data.items():
            if isinstance(value, (dict, list)) and depth < 2:
                out += _tables(value, f"{title + ' / ' if title else ''}{key}", depth + 1)
    elif isinstance(data, list) and data and all(isinstance(r, dict) for r in data):
        columns = list(dict.fromkeys(k for r in data for k, v in r.items() if not isinstance(v, (dict, list))))
        if columns:
            out += [f"\n{'#' * min(depth + 2, 6)} {title}\n", "| " + " | ".join(columns) + " |",
                    "|" + "---|" * len(columns)]
            out += ["| " + " | ".join(_cell(r.get(c, "")) for c in columns) + " |" for r in data[:MAX_ROWS]]
            if len(data) > MAX_ROWS:
                out.append(f"\n({len(data) - MAX_ROWS} more rows in the JSON file)")
    elif isinstance(data, list) and data:
        out += [f"\n{title}: {', '.join(_cell(v) for v in data[:MAX_ROWS])}\n"]
    return out


def _plot(data: Any, path: Path) -> bool:
    """For a result without a plot of its own: run time per method (a box per method where there
    are many runs, a bar where there is one), from its first list of records with a method and a
    time. False where there is no such list."""
    records = next((v for v in (data.values() if isinstance(data, dict) else [])
                    if isinstance(v, list) and v and all(isinstance(r, dict) and "method" in r for r in v)), None)
    key = next((k for k in ("median_s", "time_s") if records and all(k in r for r in records)), None)
    if key is None:
        return False
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups: dict[str, list[float]] = {}
    for r in records:
        label = " / ".join(str(r[k]) for k in ("method", "solver") if k in r)
        groups.setdefault(label, []).append(float(r[key]))
    fig, ax = plt.subplots(figsize=(6.5, 0.5 + 0.45 * len(groups)))
    labels = list(groups)
    if all(len(v) == 1 for v in groups.values()):
        ax.barh(labels, [v[0] for v in groups.values()])
    else:
        ax.boxplot(list(groups.values()), vert=False, tick_labels=labels)
    ax.set_xlabel(f"{key} (s)")
    ax.set_title("run time per method (from the JSON file)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return True


def _page(stem: str, files: list[Path], outdir: Path) -> tuple[str, dict[str, str]]:
    by_ext = {p.suffix: p for p in files}
    data = json.loads(by_ext[".json"].read_text(encoding="utf-8")) if ".json" in by_ext else {}
    report = by_ext[".md"].read_text(encoding="utf-8") if ".md" in by_ext else ""
    raw = report + (by_ext[".json"].read_text(encoding="utf-8") if ".json" in by_ext else "")
    raw = "\n".join(line for line in raw.splitlines() if not line.startswith("Versions:"))
    meta = {"date": _date(data, stem), "device": _device(data, report), "peer": _peers(raw),
            "load": _load(data)}
    heading = re.match(r"# (.+)\n", report)
    title = heading.group(1) if heading else stem
    body = report[heading.end():] if heading else ""
    lines = [f"# {title}\n", "| | |", "|---|---|", f"| result | `{stem}` |",
             f"| files | {', '.join(f'`bench/results/{p.name}`' for p in files)} |",
             f"| date | {meta['date']} |", f"| device | {meta['device']} |",
             f"| peer (compared in the same run) | {meta['peer']} |", f"| host load at the start | {meta['load']} |",
             ""]
    if ".png" in by_ext:
        shutil.copyfile(by_ext[".png"], outdir / by_ext[".png"].name)
        if by_ext[".png"].name not in body:
            lines.append(f"![{stem}]({by_ext['.png'].name})\n")
    if ".png" not in by_ext and data and _plot(data, outdir / f"{stem}-times.png"):
        lines.append(f"![run time per method]({stem}-times.png)\n")
    if body:
        lines.append(re.sub(r"^(#{1,5}) ", r"#\1 ", body, flags=re.MULTILINE))
    elif data:
        lines += ["## Data (from the JSON file)\n", *_tables(data)]
    return "\n".join(lines) + "\n", meta


def write_pages(outdir: Path) -> list[str]:
    """Write one page per result stem and the index; the stems, newest first."""
    if outdir.exists():
        shutil.rmtree(outdir)
    outdir.mkdir(parents=True)
    stems: dict[str, list[Path]] = {}
    for path in sorted(RESULTS.glob("*")):
        if path.suffix in (".json", ".md", ".png") and path.name != "README.md":  # README: the folder's note
            stems.setdefault(path.name[: -len(path.suffix)], []).append(path)
    rows = []
    for stem in sorted(stems, reverse=True):
        text, meta = _page(stem, stems[stem], outdir)
        (outdir / f"{stem}.md").write_text(text, encoding="utf-8")
        rows.append(f"| [{stem}]({stem}.md) | {meta['date']} | {meta['device']} | {meta['peer']} |")
    index = ["# Benchmark results\n",
             "Every result stored in `bench/results/`, newest first, generated when the site is built. "
             "How to run them: {doc}`../guide/benchmarks`. Timings depend on the device and on the load "
             "of the host at the time; each page says both.\n",
             "| result | date | device | peer |", "|---|---|---|---|", *rows, "",
             "```{toctree}", ":hidden:", "", *sorted(stems, reverse=True), "```", ""]
    (outdir / "index.md").write_text("\n".join(index), encoding="utf-8")
    return list(stems)


def _on_config(app, config) -> None:
    write_pages(Path(app.srcdir) / "benchmarks")


def setup(app):
    app.connect("config-inited", _on_config)
    return {"version": "1.0", "parallel_read_safe": True}
