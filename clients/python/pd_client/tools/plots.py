"""PNG plots of pd-record CSVs, like the paper's figures (needs matplotlib: the ``plots`` extra).

Importing this module raises ImportError when matplotlib is missing.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only, no display needed

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.axes import Axes  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from .record_csv import read_csv  # noqa: E402


def _load(csv_path: str | Path) -> tuple[list[str], dict[str, np.ndarray]]:
    """A CSV's columns, keeping only the rows with truth when there are any (predictions
    made after the simulator stopped would otherwise stretch the plots)."""
    names, cols = read_csv(csv_path)
    if names:
        has_truth = ~np.isnan(cols[f"true_{names[0]}"])
        if has_truth.any():
            cols = {c: v[has_truth] for c, v in cols.items()}
    return names, cols


def _axes(n: int, title: str) -> tuple[Figure, list[Axes]]:
    """A figure of ``n`` stacked axes sharing the x axis."""
    fig, axes = plt.subplots(n, 1, figsize=(8, 1.9 * n + 0.8), sharex=True, squeeze=False)
    fig.suptitle(title)
    return fig, list(axes[:, 0])


def _save(fig: Figure, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def render_session(session: str, csv_path: str | Path, out_dir: str | Path) -> list[Path]:
    """Three PNGs for one session: states (predicted vs truth), error (with the predicted
    +-2 sigma band), variance. The x axis is the prediction's target step k: a prediction of
    x(k) made lead steps earlier is drawn at k, against the truth at k."""
    names, cols = _load(csv_path)
    out = Path(out_dir)
    k = cols["step"]
    order = np.argsort(k, kind="stable")
    k = k[order]
    paths = []

    fig, axes = _axes(len(names), f"{session}: predicted state vs truth")
    for ax, name in zip(axes, names, strict=True):
        ax.plot(k, cols[f"true_{name}"][order], "k-", lw=1.2, label="truth")
        ax.plot(k, cols[f"x_{name}"][order], "C1--", lw=1.2, label="predicted")
        ax.set_ylabel(name)
        ax.grid(alpha=0.3)
    axes[0].legend(loc="best", fontsize=8)
    axes[-1].set_xlabel("target step k")
    paths.append(_save(fig, out / f"{session}-states.png"))

    fig, axes = _axes(len(names), f"{session}: prediction error (predicted - truth)")
    for ax, name in zip(axes, names, strict=True):
        sd = np.sqrt(np.maximum(cols[f"var_{name}"][order], 0.0))
        ax.fill_between(k, -2 * sd, 2 * sd, color="C0", alpha=0.2, label="±2σ predicted")
        ax.plot(k, cols[f"err_{name}"][order], "C3-", lw=1.0, label="error")
        ax.axhline(0.0, color="k", lw=0.5)
        ax.set_ylabel(name)
        ax.grid(alpha=0.3)
    axes[0].legend(loc="best", fontsize=8)
    axes[-1].set_xlabel("target step k")
    paths.append(_save(fig, out / f"{session}-error.png"))

    fig, axes = _axes(len(names), f"{session}: prediction variance")
    for ax, name in zip(axes, names, strict=True):
        ax.plot(k, cols[f"var_{name}"][order], "C0-", lw=1.2)
        ax.set_ylabel(f"var {name}")
        ax.set_yscale("log")
        ax.grid(alpha=0.3, which="both")
    axes[-1].set_xlabel("target step k")
    paths.append(_save(fig, out / f"{session}-variance.png"))
    return paths


def render_comparison(csvs: dict[str, str | Path], out_dir: str | Path) -> Path:
    """Predicted variance of every state, one line per session, in one PNG."""
    loaded = {s: _load(p) for s, p in csvs.items()}
    names = next(iter(loaded.values()))[0]
    fig, axes = _axes(len(names), "prediction variance by session")
    for i, (session, (snames, cols)) in enumerate(loaded.items()):
        order = np.argsort(cols["step"], kind="stable")
        for ax, name in zip(axes, names, strict=True):
            if name in snames:
                ax.plot(cols["step"][order], cols[f"var_{name}"][order], f"C{i}-", lw=1.2,
                        label=session)
    for ax, name in zip(axes, names, strict=True):
        ax.set_ylabel(f"var {name}")
        ax.set_yscale("log")
        ax.grid(alpha=0.3, which="both")
    axes[0].legend(loc="best", fontsize=8)
    axes[-1].set_xlabel("target step k")
    return _save(fig, Path(out_dir) / "compare-variance.png")


def render(csvs: dict[str, str | Path], out_dir: str | Path) -> list[Path]:
    """Every PNG for these sessions' CSVs; returns the paths written."""
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    paths: list[Path] = []
    for session, path in csvs.items():
        paths += render_session(session, path, out_dir)
    if len(csvs) > 1:
        paths.append(render_comparison(csvs, out_dir))
    return paths
