"""Figures of the eval stage and the report (matplotlib, Agg backend, PNG).

Each function draws one figure and returns it; ``save`` writes a PNG and closes
it (figures are many, memory is not).
"""

from __future__ import annotations

import io
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from clothgap.files import atomic_path  # noqa: E402
from eval import classes  # noqa: E402


def save(fig, path: Path, dpi: int = 110) -> Path:
    try:
        with atomic_path(path, keep_suffix=True) as tmp:
            fig.savefig(tmp, dpi=dpi, bbox_inches="tight")
    finally:
        plt.close(fig)
    return path


def png_bytes(fig, dpi: int = 110) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return buf.getvalue()


def confusion(counts: np.ndarray, title: str, true_classes: list[int] | None = None):
    """Row-normalised confusion matrix over the classes that occur.

    Rows: the true classes (the run's classes when given), columns: those plus any
    class predicted. A 54 x 54 grid of mostly empty rows would hide a 4-class study.
    """
    rows = sorted(set(true_classes) if true_classes else set(np.flatnonzero(counts.sum(axis=1))))
    cols = sorted(set(rows) | set(np.flatnonzero(counts.sum(axis=0))))
    sub = counts[np.ix_(rows, cols)].astype(float)
    norm = sub / np.maximum(sub.sum(axis=1, keepdims=True), 1)
    size = max(3.0, 0.22 * len(cols) + 1.5)
    fig, ax = plt.subplots(figsize=(size + 1.0, max(2.5, 0.22 * len(rows) + 1.5)))
    im = ax.imshow(norm, cmap="viridis", vmin=0, vmax=1, aspect="auto")
    fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04, label="fraction of true class")
    few = len(cols) <= 16
    ax.set_xticks(range(len(cols)), [classes.label(c) if few else str(c) for c in cols],
                  rotation=90, fontsize=7 if few else 5)
    ax.set_yticks(range(len(rows)), [classes.label(c) if few else str(c) for c in rows], fontsize=7 if few else 5)
    if len(rows) * len(cols) <= 100:
        for i in range(len(rows)):
            for j in range(len(cols)):
                if sub[i, j]:
                    ax.text(j, i, f"{int(sub[i, j])}", ha="center", va="center", fontsize=7,
                            color="white" if norm[i, j] < 0.6 else "black")
    ax.set_xlabel("predicted class")
    ax.set_ylabel("true class")
    ax.set_title(title, fontsize=9)
    return fig


def learning_curves(metrics: pd.DataFrame, title: str):
    """Loss and accuracy per epoch from a train folder's metrics.csv."""
    fig, (ax_loss, ax_acc) = plt.subplots(1, 2, figsize=(7.5, 2.8))
    for col, style in (("train", "-"), ("val", "--")):
        if f"{col}_loss" in metrics and metrics[f"{col}_loss"].notna().any():
            ax_loss.plot(metrics["epoch"], metrics[f"{col}_loss"], style, label=col)
        if f"{col}_acc" in metrics and metrics[f"{col}_acc"].notna().any():
            ax_acc.plot(metrics["epoch"], 100 * metrics[f"{col}_acc"], style, label=col)
    ax_loss.set(xlabel="epoch", ylabel="loss")
    ax_acc.set(xlabel="epoch", ylabel="accuracy %")
    for ax in (ax_loss, ax_acc):
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=8)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    return fig


def gap_heatmap(matrix: pd.DataFrame, title: str):
    """Accuracy (%) with rows = train variant, columns = test variant; diagonal = in-domain."""
    fig, ax = plt.subplots(figsize=(1.2 * matrix.shape[1] + 2.2, 0.8 * matrix.shape[0] + 1.6))
    values = 100 * matrix.to_numpy(dtype=float)
    im = ax.imshow(values, cmap="magma", vmin=0, vmax=100)
    fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04, label="accuracy %")
    ax.set_xticks(range(matrix.shape[1]), matrix.columns, rotation=30, ha="right")
    ax.set_yticks(range(matrix.shape[0]), matrix.index)
    for i in range(values.shape[0]):
        for j in range(values.shape[1]):
            if np.isfinite(values[i, j]):
                ax.text(j, i, f"{values[i, j]:.0f}", ha="center", va="center",
                        color="white" if values[i, j] < 60 else "black", fontsize=9)
    ax.set_xlabel("tested on")
    ax.set_ylabel("trained on")
    ax.set_title(title, fontsize=9)
    return fig


def frame_grid(images: dict[str, list[np.ndarray]], frame_labels: list[str]):
    """Rows = variants (or videos), columns = frames: the same clip side by side."""
    names = list(images)
    ncols = max(len(v) for v in images.values())
    fig, axes = plt.subplots(len(names), ncols, figsize=(1.6 * ncols + 0.6, 1.6 * len(names) + 0.2), squeeze=False)
    for i, name in enumerate(names):
        for j in range(ncols):
            ax = axes[i, j]
            ax.set_xticks([])
            ax.set_yticks([])
            if j < len(images[name]):
                ax.imshow(images[name][j])
            if j == 0:
                ax.set_ylabel(name, fontsize=8)
            if i == len(names) - 1 and j < len(frame_labels):
                ax.set_xlabel(frame_labels[j], fontsize=7)
    fig.tight_layout()
    return fig


def axis_ranking(ranking: pd.DataFrame):
    """Render axes by mean accuracy gain (% points) with their intervals; clean pairs solid, confounded hatched."""
    ranking = ranking.iloc[::-1]            # largest gain on top
    gain = 100 * ranking["mean_gain"].to_numpy(float)
    lo = 100 * ranking.get("mean_gain_lo", pd.Series(np.nan, ranking.index)).to_numpy(float)
    hi = 100 * ranking.get("mean_gain_hi", pd.Series(np.nan, ranking.index)).to_numpy(float)
    err = np.where(np.isfinite(lo) & np.isfinite(hi), np.abs(np.stack([gain - lo, hi - gain])), 0.0)
    clean = ranking["clean"].astype(bool).to_numpy()
    fig, ax = plt.subplots(figsize=(6.0, 0.45 * len(ranking) + 1.3))
    y = np.arange(len(ranking))
    bars = ax.barh(y, gain, xerr=err, color=np.where(gain >= 0, "tab:blue", "tab:red"), alpha=0.8,
                   error_kw={"ecolor": "black", "capsize": 3, "lw": 1})
    for bar, is_clean in zip(bars, clean):
        if not is_clean:
            bar.set_hatch("//")
    ax.axvline(0, color="black", lw=0.8)
    ax.set_yticks(y, [f"{a}{'' if c else ' (confounded)'}" for a, c in zip(ranking["axis"], clean)], fontsize=8)
    ax.set_xlabel("accuracy won back by matching the test variant on this axis (% points, 95% interval)")
    ax.grid(axis="x", alpha=0.3)
    fig.tight_layout()
    return fig


def measured_scatter(table: pd.DataFrame):
    """Predicted against measured bending and stretching stiffness of the measured fabrics, one colour per
    training variant (a point per model and fabric; on the diagonal, the prediction is the measurement)."""
    fig, axes = plt.subplots(1, 2, figsize=(9.0, 4.0))
    variants = list(dict.fromkeys(table["train_variant"]))
    colours = {v: plt.cm.tab10(i % 10) for i, v in enumerate(variants)}
    markers = dict(zip(dict.fromkeys(table["model"]), "osD^v<>px"))
    for ax, (what, unit) in zip(axes, (("bending", "N*m"), ("stretching", "N/m"))):
        x, y = table[f"{what}_N_m"].to_numpy(float), table[f"pred_{what}_N_m"].to_numpy(float)
        for (variant, model), g in table.groupby(["train_variant", "model"], sort=False):
            ax.scatter(g[f"{what}_N_m"], g[f"pred_{what}_N_m"], color=colours[variant], marker=markers[model],
                       s=28, alpha=0.85, label=f"{model} trained on {variant}")
        ok = np.isfinite(x) & np.isfinite(y) & (x > 0) & (y > 0)
        if ok.any():
            lo, hi = min(x[ok].min(), y[ok].min()) / 1.5, max(x[ok].max(), y[ok].max()) * 1.5
            ax.plot([lo, hi], [lo, hi], "k--", lw=0.8)
            ax.set_xscale("log")
            ax.set_yscale("log")
        ax.set(xlabel=f"measured {what} ({unit})", ylabel=f"predicted {what} ({unit})")
        ax.grid(alpha=0.3, which="both")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    return fig
