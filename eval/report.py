"""One self-contained HTML report of a run: ``report/report.html``.

Everything is inside the file (figures as base64 PNG, or JPEG where that is smaller for a figure
of rendered frames; styles inline), so it can be mailed or attached to an issue. Of the
confusion matrices it holds the in-domain and test-only cells only: a study's cross-variant
cells number in the dozens, and their numbers are in eval/results.csv and eval/domain_gap.csv.
Sections appear only when their inputs exist:
the eval tables (``clothgap eval``), learning curves (train folders), sample
frames (render folders), the sim stage's sensitivity analysis (``sim_analysis/``),
the measured-fabric set (``eval/measured.csv``, ``clothgap eval measured``) and
real-video tables (``eval/real*/``).
Every table row names the run folder, config and checkpoint(s) it came from; paths
inside the run (config, checkpoints, source CSVs) are relative links from
``report/``, so they open while the report sits in its run folder.
"""

from __future__ import annotations

import base64
import html
import io
import json
import os
import time
from pathlib import Path

import numpy as np
import pandas as pd

from clothgap.errors import ConfigError
from clothgap.runs import Run, atomic_write_text, is_done
from clothgap.settings import to_dict
from eval import figures, metrics, tables
from eval.metrics import Estimate
from eval.trained import grid_models

_CSS = """
body{font-family:-apple-system,Segoe UI,Helvetica,Arial,sans-serif;margin:0;color:#1d232a;background:#f6f7f9}
main{max-width:1180px;margin:0 auto;padding:24px 32px 64px;background:#fff}
h1{font-size:1.6em;margin-bottom:.2em}h2{border-bottom:2px solid #e3e6ea;padding-bottom:.2em;margin-top:2em}
h3{font-size:1.05em;margin:1.4em 0 .4em}
.meta{color:#5b6570;font-size:.9em}code{background:#f0f2f4;padding:1px 4px;border-radius:3px;font-size:.88em}
table{border-collapse:collapse;margin:.6em 0 1em;font-size:.86em;display:block;max-width:100%;overflow-x:auto}
th,td{border:1px solid #dde1e5;padding:4px 8px;text-align:left;vertical-align:top}
th{background:#eef1f4}tr:nth-child(even) td{background:#fafbfc}
td.num{text-align:right;font-variant-numeric:tabular-nums;white-space:nowrap}
.ci{color:#7a848e;font-size:.85em}td.na{color:#8a939c;font-size:.8em;font-style:italic}.figs{display:flex;flex-wrap:wrap;gap:14px}
figure{margin:0}figure img{max-width:100%;border:1px solid #e3e6ea}figcaption{font-size:.8em;color:#5b6570}
nav a{margin-right:12px}details{margin:.5em 0}summary{cursor:pointer;color:#2a5d9f}
pre{background:#f0f2f4;padding:10px;overflow:auto;font-size:.8em;max-height:420px}
.note{background:#fff8e1;border-left:4px solid #f2c94c;padding:6px 10px;font-size:.9em}
"""


def _esc(x) -> str:
    return html.escape(str(x))


def _img(image: bytes, caption: str = "", width: int | None = None, mime: str = "image/png") -> str:
    data = base64.b64encode(image).decode("ascii")
    style = f' style="max-width:{width}px"' if width else ""
    cap = f"<figcaption>{_esc(caption)}</figcaption>" if caption else ""
    return f'<figure><img alt="{_esc(caption)}"{style} src="data:{mime};base64,{data}">{cap}</figure>'


def _img_file(path: Path, caption: str, width: int | None = None) -> str:
    return _img(path.read_bytes(), caption, width)


# A figure of rendered frames at 112 px is a photograph: at this quality JPEG holds it in a sixth of the PNG's
# bytes (10 variants' sample frames 1.1 MB -> 0.16 MB, their conv5 overlays 2.6 MB -> 0.43 MB). Frames of a
# few dozen pixels, drawn as flat blocks, stay smaller as PNG.
PHOTO_JPEG_QUALITY = 85
# Learning curves show at most 560 px wide: a 7.5 in figure at this dpi is that wide, at 110 dpi 825 px.
CURVES_DPI = 80


def _photo(png: bytes, caption: str = "", width: int | None = None) -> str:
    """A figure of rendered frames (sample frames, conv5 overlays): as JPEG when that is smaller than the PNG."""
    from PIL import Image

    with Image.open(io.BytesIO(png)) as image:
        rgb = image.convert("RGB")          # matplotlib's PNGs are opaque: nothing is lost with the alpha channel
    jpeg = io.BytesIO()
    rgb.save(jpeg, "JPEG", quality=PHOTO_JPEG_QUALITY, optimize=True)
    if len(jpeg.getvalue()) < len(png):
        return _img(jpeg.getvalue(), caption, width, "image/jpeg")
    return _img(png, caption, width)


LINK_COLUMNS = ("checkpoints", "checkpoint", "folder")


def _link(run: Run, path: Path | str) -> str:
    """A relative link from report/ to a file or folder of the run (plain code when outside the run)."""
    target = Path(path) if Path(path).is_absolute() else run.root / path
    try:
        shown = target.resolve().relative_to(run.root.resolve())
    except ValueError:
        return f"<code>{_esc(path)}</code>"
    href = os.path.relpath(target.resolve(), run.report_dir.resolve()).replace(os.sep, "/")
    return f'<a href="{_esc(href)}"><code>{_esc(shown)}</code></a>'


def _links(run: Run, paths: str) -> str:
    """Space-separated run paths (e.g. a cell's checkpoints) as links, one per line."""
    return "<br>".join(_link(run, p) for p in str(paths).split()) if isinstance(paths, str) else ""


# Why a cell of these columns can be empty: said in the cell instead of leaving it blank.
_CORRELATION_WHY = "undefined: the predictions or the truth are constant over these test clips"
WHY_EMPTY = {
    "drop": "the training variant was not tested on itself",
    "gap": "no model was trained on the test variant",
    "gain": "no model of the reference training variant (the run's first variant)",
    "in_domain_gain": "not an in-domain row, or no in-domain row of the reference training variant",
    **{c: _CORRELATION_WHY for c in tables.CORRELATION_COLUMNS},
    "mean_share": "no gap to close: the in-domain model did no better",
    "bending rank": _CORRELATION_WHY,
    "top-1 minus first (points)": "the reference recipe, or no test clip paired with it",
    "mean_gain": "no pair of training variants tells this axis apart",
    "pearson": "undefined: fewer than 3 points, or one side constant",
    "spearman": "undefined: fewer than 3 points, or one side constant",
    **{c: "not in the paper's Table 2" for c in ("paper_p_est", "paper_p", "paper_k_est", "paper_k", "p_match",
                                                 "k_match", "p_table_match", "k_table_match")},
}


def _empty(column: str, why: str | None = None) -> str:
    """An empty cell that says why it is empty."""
    return f'<td class="na">n/a: {_esc(why or WHY_EMPTY.get(column, "no value"))}</td>'


def _missing(v) -> bool:
    return v is None or (pd.api.types.is_scalar(v) and pd.isna(v))


def _table(frame: pd.DataFrame, pct: tuple[str, ...] = (), est: tuple[str, ...] = (), run: Run | None = None) -> str:
    """A frame as an HTML table; ``pct`` columns (fractions) shown as percent with their _lo/_hi,
    ``est`` columns as value [lo, hi]; with ``run``, path columns (``LINK_COLUMNS``) become links.
    An empty cell says why (``WHY_EMPTY``)."""
    shown = [c for c in frame.columns if not (c.endswith(("_lo", "_hi")) and c[:-3] in pct + est)]
    head = "".join(f"<th>{_esc(c)}</th>" for c in shown)
    rows = []
    for _, r in frame.iterrows():
        cells = []
        for c in shown:
            v = r[c]
            if _missing(v):
                cells.append(_empty(c))
            elif c in pct:
                lo, hi = r.get(f"{c}_lo", np.nan), r.get(f"{c}_hi", np.nan)
                ci = f' <span class="ci">[{100 * lo:.1f}, {100 * hi:.1f}]</span>' if pd.notna(lo) else ""
                cells.append(f'<td class="num">{100 * v:.1f}{ci}</td>')
            elif c in est:
                cells.append(_est(r, c, 1.0, 2))
            elif run is not None and c in LINK_COLUMNS:
                cells.append(f"<td>{_links(run, v)}</td>")
            elif isinstance(v, (float, np.floating)):
                cells.append(f'<td class="num">{v:.4g}</td>')
            else:
                cells.append(f"<td>{_esc(v)}</td>")
        rows.append("<tr>" + "".join(cells) + "</tr>")
    return f"<table><tr>{head}</tr>{''.join(rows)}</table>"


def _est(r, prefix: str, scale: float = 100.0, digits: int = 1, why: str | None = None) -> str:
    est = Estimate(r[prefix], r.get(f"{prefix}_lo", np.nan), r.get(f"{prefix}_hi", np.nan))
    if not np.isfinite(est.value):
        return _empty(prefix, why)
    if not (np.isfinite(est.low) and np.isfinite(est.high)):
        return f'<td class="num">{est.value * scale:.{digits}f}</td>'
    return (f'<td class="num">{est.value * scale:.{digits}f} <span class="ci">[{est.low * scale:.{digits}f}, '
            f"{est.high * scale:.{digits}f}]</span></td>")


# ------------------------------------------------------------------ sections

def _section_config(run: Run) -> str:
    cfg = run.config
    rows = [("run folder", f"<code>{_esc(run.root.resolve())}</code>"),
            ("config", _link(run, "config.json")),
            ("settings", _esc(", ".join(cfg.sim.settings()))),
            ("classes", _esc(", ".join(map(str, cfg.sim.class_indices())) if cfg.sim.classes else "all 54")),
            ("sequences per class", _esc(cfg.sim.sequences_per_class)),
            ("render variants", _esc(", ".join(cfg.render.variants))),
            ("models / seeds", _esc(f"{', '.join(cfg.train.models)} / {', '.join(map(str, cfg.train.seeds))}")),
            ("intervals", _esc(f"{100 * cfg.eval.confidence:g}% percentile bootstrap over test sequences, "
                               f"{cfg.eval.bootstrap} resamples"))]
    body = "<table>" + "".join(f"<tr><th>{k}</th><td>{v}</td></tr>" for k, v in rows) + "</table>"
    full = _esc(json.dumps(to_dict(cfg), indent=2))
    return f'<h2 id="config">Run and config</h2>{body}<details><summary>Full resolved config</summary><pre>{full}</pre></details>'


def _section_table3(run: Run) -> str:
    path = run.eval_dir / "table3.csv"
    if not path.is_file():
        return '<h2 id="table3">Table 3</h2><p class="note">No eval tables yet: run <code>clothgap eval</code>.</p>'
    table = pd.read_csv(path)
    if table.empty:
        return '<h2 id="table3">Table 3</h2><p class="note">No in-domain results in this run.</p>'
    models = tables.table3_models(table)
    head = "".join(f"<th>{h}</th>" for h in ("Motion", "Re-mesh", "Texture", "Variant"))
    head += "".join(f"<th>{_esc(tables.model_title(m))}</th>" for m in models)
    rows = []
    for _, r in table.iterrows():
        cells = "".join(f"<td>{_esc(r[c])}</td>" for c in ("motion", "remeshing", "texture", "variant"))
        cells += "".join(_est(r, f"{m}_acc") if pd.notna(r.get(f"{m}_acc"))
                         else _empty("acc", f"no {m} trained on {r['variant']}") for m in models)
        rows.append(f"<tr>{cells}</tr>")
    out = ['<h2 id="table3">Table 3: accuracy on simulated test sequences</h2>',
           "<p>Accuracy over 54 classes (% of test sub-sequences of train.clip_len frames; one a clip when it is the whole clip) of each model trained and tested on the "
           "same render variant, with the 95% interval from resampling test <em>sequences</em>. "
           f"Source: {_link(run, run.eval_dir / 'table3.csv')}. Paper (wind, Unif-1, Rand): "
           "Base-1 53.6, Base-2 53.3, CNN+LSTM 64.7.</p>",
           f"<table><tr>{head}</tr>{''.join(rows)}</table>"]
    detail_cols = (("top3", "Top-3 %", 100.0, 1), ("stretch_acc", "Stretch factor %", 100.0, 1),
                   ("bend_acc", "Bend factor %", 100.0, 1), ("class_dist", "Class distance (steps)", 1.0, 2),
                   ("seq_acc", "Per video %", 100.0, 1))
    for m in models:
        head = "".join(f"<th>{h}</th>" for h in ("Setting", "Variant", *[d[1] for d in detail_cols],
                                                  "Sequences", "Seeds", "Checkpoint(s)"))
        rows = []
        for _, r in table[table[f"{m}_acc"].notna()].iterrows():
            cells = f"<td>{_esc(r['motion'])}-{_esc(r['remeshing'])}</td><td>{_esc(r['variant'])}</td>"
            cells += "".join(_est(r, f"{m}_{key}", scale, digits) for key, _, scale, digits in detail_cols)
            cells += (f'<td class="num">{int(r[f"{m}_sequences"])}</td><td>{_esc(r[f"{m}_seeds"])}</td>'
                      f"<td>{_links(run, r[f'{m}_checkpoints'])}</td>")
            rows.append(f"<tr>{cells}</tr>")
        out.append(f"<h3>{_esc(tables.model_title(m))}: details</h3>"
                   f"<table><tr>{head}</tr>{''.join(rows)}</table>")
    return "".join(out)


def _section_confusion(run: Run) -> str:
    """The confusion matrices of the in-domain cells and of the test-only variants' cells (no model trains on
    them, e.g. heldout); the cross-variant cells are eval's files and tables, not embedded."""
    root = run.eval_dir / "figures" / "confusion"
    pngs = sorted(root.rglob("*.png")) if root.is_dir() else []
    if not pngs:
        return ""
    # Training variants: the config's and any with a model here (a test variant that is neither is test-only).
    trained = set(run.config.render.variants) | {p.relative_to(root).parts[1] for p in pngs}
    inside, test_only, others = [], [], 0
    for p in pngs:
        setting, train_v, model = p.relative_to(root).parts[:3]
        caption = f"{setting}, {model}: trained on {train_v}, tested on {p.stem}"
        if p.stem == train_v:
            inside.append(_img_file(p, caption, 460))
        elif p.stem not in trained:
            test_only.append(_img_file(p, caption, 460))
        else:
            others += 1
    out = ['<h2 id="confusion">Confusion matrices</h2><p>Rows: true class (p, k), columns: predicted class; '
           'colour = fraction of the true class, numbers = sub-sequence counts. '
           f"Files: <code>{_esc(root)}</code>.</p>", f'<div class="figs">{"".join(inside)}</div>']
    if test_only:
        out.append(f"<h3>On variants no model trains on ({_esc(', '.join(sorted({p.stem for p in pngs} - trained)))})"
                   f'</h3><div class="figs">{"".join(test_only)}</div>')
    if others:
        out.append(f"<p>The other {others} cells (a model tested on another training variant) are not shown here: "
                   f"their numbers are in {_link(run, run.eval_dir / 'results.csv')} and "
                   f"{_link(run, run.eval_dir / 'domain_gap.csv')}, their figures in {_link(run, root)}.</p>")
    return "".join(out)


def _section_learning(run: Run) -> str:
    figs = []
    for m in grid_models(run):
        path = m.folder / "metrics.csv"
        if not path.is_file():
            continue
        try:
            frame = pd.read_csv(path)
        except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError):
            continue
        if "epoch" not in frame or frame.empty:
            continue
        rel = m.folder.relative_to(run.root)
        state = "" if is_done(m.folder) else " (unfinished)"
        fig = figures.learning_curves(frame, f"{rel}{state}")
        figs.append(_img(figures.png_bytes(fig, dpi=CURVES_DPI), f"{rel}/metrics.csv", 560))
    if not figs:
        return ""
    return ('<h2 id="learning">Learning curves</h2><p>Per epoch, from each train folder\'s <code>metrics.csv</code>.</p>'
            f'<div class="figs">{"".join(figs)}</div>')


def _section_frames(run: Run) -> str:
    """The same clip in every rendered variant, a few frames each (a paired view of the variants)."""
    from eval.stage import rendered_variants
    from render.frames import FrameError, open_clip_frames

    out = []
    for setting in run.config.sim.settings():
        variants = rendered_variants(run, setting)
        if not variants:
            continue
        common = set.intersection(*(set(run.done_clips(run.render_dir(v, setting))) for v in variants))
        if not common:
            continue
        clip = sorted(common)[0]
        images, labels = {}, []
        for v in variants:
            try:  # frames.npy, or the PNGs of clips rendered without one
                frames = open_clip_frames(run.render_dir(v, setting) / clip)
            except FrameError:
                continue
            picks = sorted({0, len(frames) // 2, len(frames) - 1})
            images[v] = [np.array(frames[i]) for i in picks]
            labels = [f"frame {i}" for i in picks]
        if images:
            fig = figures.frame_grid(images, labels)
            out.append(_photo(figures.png_bytes(fig), f"{setting}, clip {clip} (render/<variant>/{setting}/{clip})"))
    if not out:
        return ""
    return ('<h2 id="frames">Sample frames per render variant</h2><p>One clip (same simulation) under every '
            f'variant that was rendered.</p><div class="figs">{"".join(out)}</div>')


def _section_activations(run: Run) -> str:
    """conv5 overlays (the paper's Fig. 6): per setting, the in-domain model on one test clip of each variant."""
    from eval.stage import finished_models, rendered_variants, test_clips

    models = sorted(finished_models(run), key=lambda m: (tables.model_sort_key(m.model) != tables.model_sort_key("lrcn"),
                                                         m.variant != run.config.render.variants[0], m.seed))
    out = []
    for setting in run.config.sim.settings():
        chosen = next((m for m in models if m.setting == setting), None)
        if chosen is None:
            continue
        try:
            from eval.activations import clip_frames, overlay_figure
            from learn.predict import load_checkpoint, load_model

            size = int(load_checkpoint(chosen.folder)["model_args"]["image_size"])
            model = load_model(chosen.folder, "cpu")
            test_ids = test_clips(run, setting)
            rows = {}
            for variant in rendered_variants(run, setting):
                folder = run.render_dir(variant, setting)
                clip = next((c for c in test_ids if is_done(folder / c)), None)
                if clip is not None:
                    rows[f"{variant} {clip}"] = clip_frames(folder / clip, size)
            if rows:
                fig = overlay_figure(rows, model)
                rel = chosen.checkpoint.relative_to(run.root)
                out.append(_photo(figures.png_bytes(fig), f"{setting}: conv5 of {rel}")
                           + f"<p>Model: {_link(run, chosen.checkpoint)}</p>")
        except Exception as err:  # a report must not fail on one figure; say why it is missing
            out.append(f'<p class="note">conv5 overlays for {_esc(setting)} skipped: {_esc(type(err).__name__)}: '
                       f"{_esc(err)}</p>")
    if not out:
        return ""
    return ('<h2 id="conv5">Where the CNN looks (conv5, Fig. 6)</h2><p>Channel mean of the last conv layer, '
            "normalised over the clip, jet colour map over the frame, for one test clip per render variant.</p>"
            + "".join(out))


def _section_gap(run: Run) -> str:
    path = run.eval_dir / "domain_gap.csv"
    if not path.is_file():
        return ""
    gap = pd.read_csv(path)
    if gap.empty:
        return ""
    out = ['<h2 id="gap">Domain gap</h2><p><b>drop</b> = in-domain accuracy of the training variant minus '
           "accuracy on the test variant; <b>gap</b> = accuracy of a model trained on the test variant minus this "
           "one's; <b>gain</b> = this accuracy minus that of the model trained on the run's first variant "
           f"({_esc(run.config.render.variants[0])}) on the same test variant: what training on this variant "
           "instead buys; <b>in_domain_gain</b> (in-domain rows) = this in-domain accuracy minus the first "
           "variant's in its own look: which look is easier to read; all with paired 95% sequence-bootstrap "
           "intervals. <b>p_spearman</b>, <b>k_spearman</b> "
           "(Spearman) and <b>p_pearson</b>, <b>k_pearson</b> (Pearson on log coefficients): correlation of the "
           "predicted class's stretching (p) and bending (k) factor with the true one over test sequences, with "
           f"95% sequence-bootstrap intervals. Source: {_link(run, path)}.</p>"]
    out.append(_gap_on_test_only_looks(run, gap))
    fig_root = run.eval_dir / "figures" / "gap"
    pngs = sorted(fig_root.rglob("*.png")) if fig_root.is_dir() else []
    if pngs:
        out.append("<p>Accuracy (%) of every model on every test variant: rows the variant it was trained on, "
                   "columns the one it was tested on; the diagonal is in-domain.</p>"
                   '<div class="figs">' + "".join(_img_file(p, str(p.relative_to(run.root)), 420) for p in pngs)
                   + "</div>")
    elif gap["train_variant"].nunique() < 2 and gap["test_variant"].nunique() < 2:
        out.append('<p class="note">One render variant: no gap to measure yet. Add variants to this run (they '
                   f"reuse its simulations): <code>clothgap pipeline {_esc(run.root)} --set "
                   "render.variants=paper,grid</code>, or <code>study.add_variants(...)</code> in "
                   "<code>clothgap.api</code>.</p>")
    corr = [f"{c}{x}" for c in tables.CORRELATION_COLUMNS for x in ("", "_lo", "_hi")]
    cols = ["setting", "model", "train_variant", "test_variant", "sequences", "acc", "acc_lo", "acc_hi",
            "drop", "drop_lo", "drop_hi", "gap", "gap_lo", "gap_hi", "gain", "gain_lo", "gain_hi", "in_domain_gain",
            "in_domain_gain_lo", "in_domain_gain_hi", *corr,
            "checkpoints"]
    out.append(_table(gap[[c for c in cols if c in gap]], pct=("acc", "drop", "gap", "gain", "in_domain_gain"),
                      est=tables.CORRELATION_COLUMNS, run=run))
    rank_path = run.eval_dir / "axis_ranking.csv"
    ranking = pd.read_csv(rank_path) if rank_path.is_file() else pd.DataFrame()
    if not ranking.empty:
        out.append("<h3>Render axes ranked by the gap they close</h3><p><b>mean_gain</b>: accuracy gained on a "
                   "test variant by training on a variant that matches it on this axis, with its 95% interval "
                   "from resampling test clips (<b>clean</b> = the two training variants differ in this axis "
                   "only; otherwise other axes changed too); <b>mean_share</b>: that gain over the gap it "
                   f"started from. Source: {_link(run, rank_path)}.</p>"
                   + _img(figures.png_bytes(figures.axis_ranking(ranking)), "axes ranked by mean gain", 560)
                   + _table(ranking, pct=("mean_gain",)))
    elif rank_path.is_file():
        out.append('<p class="note">No axis ranking: the rendered variants do not differ in a render setting, '
                   "or no two training variants were tested on a common variant.</p>")
    return "".join(out)


def _gap_on_test_only_looks(run: Run, gap: pd.DataFrame) -> str:
    """Per look that no model trained on (e.g. heldout): every training variant's model on it, best gain over
    the first variant first, with within-one, stretching and bending beside exact accuracy: the study's answer
    to which render choice carries, before the full table."""
    looks = sorted(set(gap["test_variant"]) - set(gap["train_variant"]))
    results_path = run.eval_dir / "results.csv"
    if not looks or not results_path.is_file():
        return ""
    keys = ["setting", "model", "train_variant", "test_variant"]
    scores = ["within1", "stretch_acc", "bend_acc"]
    results = pd.read_csv(results_path)
    extra = [c for s in scores for c in (s, f"{s}_lo", f"{s}_hi") if c in results]
    out = []
    for look in looks:
        rows = gap[gap["test_variant"] == look].merge(results[keys + extra], on=keys, how="left")
        rows = rows.sort_values("gain", ascending=False, na_position="last")
        cols = ["setting", "model", "train_variant", "acc", "acc_lo", "acc_hi", "gain", "gain_lo", "gain_hi", *extra]
        out.append(f"<h3>On {_esc(look)}, a look no model trained on</h3><p>Each training variant's model on the "
                   f"same test clips rendered as {_esc(look)}, the largest <b>gain</b> over the first variant's "
                   "model first.</p>"
                   + _table(rows[[c for c in cols if c in rows]], pct=("acc", "gain", *scores), run=run))
    return "".join(out)


def _csv_table(path: Path, run: Run | None = None) -> str:
    try:
        return _table(pd.read_csv(path), run=run)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as e:
        return f'<p class="note">{_esc(path.name)} could not be read: {_esc(e)}</p>'


def _section_sim_analysis(run: Run) -> str:
    root = run.sim_analysis_dir
    if not root.is_dir():
        return ""
    csvs = sorted(root.rglob("*.csv"), key=lambda p: ("table2" not in p.name.lower(), p.name))
    pngs = sorted(root.rglob("*.png"))
    if not csvs and not pngs:
        return ""
    out = ['<h2 id="sim">Material sub-space: sensitivity and Table 2</h2>'
           f"<p>From the sim stage's analysis in {_link(run, root)} (the paper's Fig. 3 and Table 2; "
           "<code>eval.sim_analysis</code> runs them, or <code>clothgap sim table2|sensitivity --out "
           f"{_esc(root)}</code>).</p>"]
    if pngs:
        out.append('<div class="figs">' + "".join(_img_file(p, str(p.relative_to(run.root)), 520) for p in pngs)
                   + "</div>")
    for p in csvs:
        out.append(f"<h3>{_link(run, p)}</h3>{_csv_table(p, run)}")
    return "".join(out)


def _measured_geometry(run: Run) -> str:
    """What the measured fabrics' simulated geometry tells plain classifiers (``clothgap eval learnability
    --measured``): per setting and classifier, the fabrics within one bin of Table 2 and the bending rank."""
    path = run.eval_dir / "learnability-measured.json"
    if not path.is_file():
        return ""
    from eval.learnability import measured_reading      # (imports torch: only when there is something to show)

    try:
        reports = json.loads(path.read_text())["settings"]
        rows = []
        for rep in reports:
            for r in rep["results"]:
                read = measured_reading(r)
                rows.append(f"<tr><td>{_esc(rep['setting'])}</td><td>{_esc(r['classifier'])}</td>"
                            f"<td class=\"num\">{read['within1_fabrics']} of {read['fabrics']}</td>"
                            f"<td class=\"num\">{read['class_dist']:.1f}</td>"
                            + _est(read["bending_rank"], "spearman", 1.0, 2, _CORRELATION_WHY)
                            + f"<td>{rep['clip_len']} frames</td></tr>")
    except (KeyError, TypeError, ValueError, UnicodeDecodeError) as e:     # JSONDecodeError is a ValueError
        return f'<h3>The fabrics\' simulated geometry</h3><p class="note">{_link(run, path)} unreadable: {_esc(e)}</p>'
    head = "".join(f"<th>{h}</th>" for h in ("Setting", "Classifier", "Fabrics within one bin of Table 2",
                                             "Grid steps", "Bending rank vs measured bending (Spearman)", "Window"))
    return ("<h3>The fabrics' simulated geometry</h3><p>Plain classifiers trained on the true 8 x 8 lattices of the "
            "run's class clips read the measured fabrics' clips (<code>clothgap eval learnability RUN --measured "
            f"N</code>; {_link(run, path)}): how much of the set the simulation itself carries, before any pixel. "
            "A floor on it: the classifiers are plain.</p>"
            f"<table><tr>{head}</tr>{''.join(rows)}</table>")


def _section_measured(run: Run) -> str:
    """The measured-fabric set (eval.measured): per model, fabrics against Table 2, match rates, correlations;
    and what the fabrics' simulated geometry tells (``_measured_geometry``)."""
    path = run.eval_dir / "measured.csv"
    geometry = _measured_geometry(run)
    if not path.is_file():
        return ('<h2 id="measured">Measured fabrics (the paper\'s Table 2 classes)</h2>' + geometry) if geometry else ""
    try:
        table = pd.read_csv(path)
        corr_path = run.eval_dir / "measured_correlations.csv"
        corr = pd.read_csv(corr_path) if corr_path.is_file() else pd.DataFrame()
        info = json.loads((run.eval_dir / "measured.json").read_text()) if (run.eval_dir / "measured.json").is_file() \
            else {}
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError, json.JSONDecodeError) as e:
        return (f'<h2 id="measured">Measured fabrics</h2><p class="note">measured tables unreadable: {_esc(e)}</p>'
                + geometry)
    variant = info.get("variant", table["test_variant"].iloc[0] if len(table) else "?")
    note = "" if info.get("heldout", True) else (' <span class="note">This variant is also a training variant: '
                                                  "the set is not held out.</span>")
    out = ['<h2 id="measured">Measured fabrics (the paper\'s Table 2 classes)</h2>'
           f"<p>The Wang et al. 2011 fabrics simulated with their own measured tables (not the scaled basis), "
           f"{info.get('sequences', '?')} sequence(s) per fabric and setting, rendered in the held-out variant "
           f"<code>{_esc(variant)}</code>{note}, and predicted through the real-video path (mean sub-sequence "
           "probabilities per clip, then per fabric). <b>Exact</b>, <b>p</b>, <b>k</b>: the prediction matches the "
           "class, stretching or bending factor the paper's Table 2 gives the fabric; <b>steps</b>: grid steps "
           "between them. Measured stiffness from the tables: stretching = mean at-rest k0, k2, k3 (N/m), "
           "bending = mean of the bending table (N*m); a class predicts p or k times the basis fabric's value. "
           f"Sources: {_link(run, path)}, {_link(run, run.eval_dir / 'measured_correlations.csv')}, "
           f"{_link(run, run.eval_dir / 'measured.md')}, clips in {_link(run, run.measured_root)}.</p>"]
    if not table.empty:
        out.append("<p>Which training variant carries to the measured fabrics: each fabric's predicted stiffness "
                   "against its measured one, one colour per training variant (on the dashed diagonal the "
                   "prediction is the measurement; the class grid makes the predictions step).</p>"
                   + _img(figures.png_bytes(figures.measured_scatter(table)), "measured fabrics, all models", 760))
    for key, g in table.groupby(_MEASURED_KEYS, sort=True):
        out += _measured_model(run, key, g, info, corr)
    out.append(_measured_ensembles(run, info))
    return "".join(out) + geometry


def _measured_ensembles(run: Run, info: dict) -> str:
    """The seeds' ensembles (``eval.measured.score_ensemble``): one row each, its match rates and bending rank."""
    rows = []
    for e in info.get("ensembles", []):
        match = {m["score"]: m for m in e.get("match", [])}
        bend = next((c for c in e.get("correlations", []) if c.get("unit") == "fabric"
                     and c.get("score") == "pred_bending_N_m" and c.get("target") == "bending_N_m"), {})
        row = {"model": tables.model_title(e["model"]), "trained on": e["train_variant"], "setting": e["setting"],
               "seeds": " + ".join(map(str, e.get("ensemble_of", [])))}
        cells = [(score, match[score], "value") for score in ("within1", "exact", "k_within1_tables") if score in match]
        cells += [("bending rank", bend, "spearman")] if bend else []
        for column, found, field in cells:       # value, lo, hi; a JSON null (an undefined interval) as NaN
            row.update({f"{column}{end}": np.nan if found[f"{field}{end}"] is None else found[f"{field}{end}"]
                        for end in ("", "_lo", "_hi")})
        rows.append(row)
    if not rows:
        return ""
    return ("<h3>Seeds' ensembles</h3><p>The models that differ only in their seed, read together (per clip the mean "
            "of their probabilities), over fabrics with 95% intervals. <b>within1</b>, <b>exact</b>: against Table "
            "2's class; <b>k_within1_tables</b>: the bending factor within one step of the class the fabric's own "
            "tables give (a diagnostic: nearest to its measured stretching and bending over the basis's); "
            "<b>bending rank</b>: Spearman of the predicted against the measured bending over fabrics. Per fabric: "
            f"{_link(run, run.eval_dir / 'measured_ensembles.csv')}.</p>"
            + _table(pd.DataFrame(rows), est=("within1", "exact", "k_within1_tables", "bending rank")))


_MEASURED_KEYS = ["setting", "train_variant", "model", "seed", "test_variant"]   # one model on the measured set


def _measured_model(run: Run, key: tuple, g: pd.DataFrame, info: dict, corr: pd.DataFrame) -> list[str]:
    """One model's part of the measured section: its fabrics against Table 2, match rates, correlations, figures."""
    keys = _MEASURED_KEYS
    setting, train_v, model, seed, _ = key
    out = [f"<h3>{_esc(tables.model_title(model))} trained on {_esc(train_v)} "
           f"({_esc(setting)}, seed {_esc(seed)})</h3><p>Model: {_links(run, g['checkpoint'].iloc[0])}; "
           f"per-clip predictions and Table 4: {_links(run, g['folder'].iloc[0])}</p>",
           _measured_fabrics_table(g)]
    entry = next((e for e in info.get("models", []) if [e.get(k) for k in keys[:4]] == list(key[:4])), {})
    if entry.get("match"):
        match = pd.DataFrame(entry["match"])
        out.append("<p>Match over fabrics (95% interval resampling fabrics):</p>"
                   + _table(match[["score", "fabrics", "value", "value_lo", "value_hi"]], est=("value",)))
    if not corr.empty:
        sub = corr[np.logical_and.reduce([corr[k] == v for k, v in zip(keys, key)])]
        cols = ["unit", "description", "n", "fabrics", "pearson", "pearson_lo", "pearson_hi", "spearman",
                "spearman_lo", "spearman_hi"]
        out.append("<p>Correlation with measured values (unit <b>clip</b>: one point per clip, intervals "
                   "resample whole fabrics; <b>fabric</b>: one point per fabric):</p>"
                   + _table(sub[[c for c in cols if c in sub]], est=("pearson", "spearman")))
    folder = run.root / g["folder"].iloc[0]
    scatter, overlays = folder / "scatter.png", folder / "activations.png"     # a plot; rendered frames
    out.append('<div class="figs">'
               + (_img_file(scatter, str(scatter.relative_to(run.root)), 520) if scatter.is_file() else "")
               + (_photo(overlays.read_bytes(), str(overlays.relative_to(run.root)), 520) if overlays.is_file()
                  else "") + "</div>")
    return out


def _measured_fabrics_table(g: pd.DataFrame) -> str:
    """One model's fabrics: predicted class against Table 2's, and measured against predicted stiffness."""
    head = "".join(f"<th>{h}</th>" for h in ("Fabric", "Clips", "Predicted (p, k)", "Prob.", "Table 2 (p, k)",
                                              "Exact", "p", "k", "Within one bin", "Steps",
                                              "Bending measured / predicted",
                                              "Stretching measured / predicted", "Density"))
    rows = []
    for _, r in g.iterrows():
        yes = lambda x: "yes" if x == 1 else "no"  # noqa: E731
        rows.append(f"<tr><td>{_esc(r['fabric'])}</td><td class=\"num\">{r['clips']}</td>"
                    f"<td>({r['pred_p']:g}, {r['pred_k']:g})</td><td class=\"num\">{r['prob']:.2f}</td>"
                    f"<td>({r['table2_p']:g}, {r['table2_k']:g})</td><td>{yes(r['exact'])}</td>"
                    f"<td>{yes(r['p_match'])}</td><td>{yes(r['k_match'])}</td>"
                    # (derived: a measured.csv written before the column has none)
                    f"<td>{yes(metrics.within_one_bin([r['table2_class']], [r['pred']])[0])}</td>"
                    f"<td class=\"num\">{r['class_dist']:g}</td>"
                    f"<td class=\"num\">{r['bending_N_m']:.3g} / {r['pred_bending_N_m']:.3g}</td>"
                    f"<td class=\"num\">{r['stretching_N_m']:.4g} / {r['pred_stretching_N_m']:.4g}</td>"
                    f"<td class=\"num\">{r['density_kg_m2']:.3g}</td></tr>")
    return f"<table><tr>{head}</tr>{''.join(rows)}</table>"


ABLATION_KEYS = ("acc", "within1", "stretch_acc", "bend_acc", "acc_minus_first")
ABLATION_COLUMNS = {"acc": "top-1 %", "within1": "within one step %", "stretch_acc": "stretching %",
                    "bend_acc": "bending %", "acc_minus_first": "top-1 minus first (points)"}


def _ablation_reports(run: Run) -> list[tuple[Path, dict]]:
    """The recipe comparisons `clothgap eval ablation` (or scripts/gpu/learn_grid.py) wrote under eval/."""
    found = []
    for path in sorted(run.eval_dir.glob("*.json")):
        try:
            report = json.loads(path.read_text())
        except (OSError, ValueError):
            continue
        if isinstance(report, dict) and report.get("recipes") and isinstance(report["recipes"], list) \
                and "base_train" in report:
            found.append((path, report))
    return found


def _ablation_frame(recipes: list[dict], look: str | None) -> pd.DataFrame:
    """One row per recipe x model: its scores in its training look (``look`` None) or in test-only ``look``."""
    rows = []
    for r in recipes:
        scores = r if look is None else (r.get("on") or {}).get(look) or {}
        row = {"recipe": r["recipe"], "model": r["model"], "seeds": ", ".join(map(str, r.get("seeds", [])))}
        for key in ABLATION_KEYS:
            for suffix in ("", "_lo", "_hi"):
                row[key + suffix] = scores.get(key + suffix, np.nan)
        if look is None:
            kept = [s.get("kept_epoch") for s in r.get("speed") or []]
            row["kept epoch"] = ", ".join("-" if k is None else str(k) for k in kept) or np.nan
        rows.append(row)
    frame = pd.DataFrame(rows)
    for suffix in ("", "_lo", "_hi"):
        frame["acc_minus_first" + suffix] *= 100     # points, shown as value [lo, hi] like the other estimates
    return frame.rename(columns={key + suffix: ABLATION_COLUMNS[key] + suffix
                                 for key in ABLATION_KEYS for suffix in ("", "_lo", "_hi")})


def _section_ablations(run: Run) -> str:
    """Every recipe comparison under eval/: each recipe in its training look and in each test-only look."""
    parts = []
    pct = tuple(ABLATION_COLUMNS[k] for k in ABLATION_KEYS[:4])
    est = (ABLATION_COLUMNS["acc_minus_first"],)
    for path, report in _ablation_reports(run):
        recipes = report["recipes"]
        parts.append(f"<h3>{_esc(report.get('setting', ''))} / {_esc(report.get('variant', ''))}: "
                     f"{_link(run, path)}</h3><p>{report.get('test_sequences', '?')} test sequences; the difference "
                     "is paired with the first recipe on the same clips.</p>"
                     + _table(_ablation_frame(recipes, None), pct=pct, est=est))
        for look in report.get("test_variants", []):
            parts.append(f"<p>The same test clips rendered as <code>{_esc(look)}</code>, a look the recipes did "
                         "not train on:</p>" + _table(_ablation_frame(recipes, look), pct=pct, est=est))
    if not parts:
        return ""
    return ('<h2 id="ablations">Training recipes</h2><p>Recipes compared on the same test clips '
            "(<code>clothgap eval ablation</code>): exact class, within one grid step, stretching and bending, "
            "with 95 % intervals over test sequences.</p>" + "".join(parts))


def _section_extra_tables(run: Run) -> str:
    """Real-video (Table 4) outputs written under eval/real*/ (and measured-fabric folders a user wrote
    under eval/measured*/ with --out; the run's own eval/measured/ is the measured section's)."""
    parts = []
    for pattern, title in (("real*", "Real videos (Table 4)"), ("measured*", "Measured fabrics")):
        for folder in sorted(run.eval_dir.glob(pattern)):
            if not folder.is_dir() or folder == run.eval_dir / "measured":
                continue
            for p in sorted(folder.glob("*.csv")):
                parts.append(f"<h3>{_esc(title)}: {_link(run, p)}</h3>{_csv_table(p, run)}")
            parts += [_photo(p.read_bytes(), str(p.relative_to(run.root)), 520) if p.name == "activations.png"
                      else _img_file(p, str(p.relative_to(run.root)), 520) for p in sorted(folder.glob("*.png"))]
    return '<h2 id="real">Real and measured data</h2>' + "".join(parts) if parts else ""


def write_report(run: Run) -> Path:
    """Write ``report/report.html`` for the run (sections for whatever stages have finished).

    Refuses (ConfigError) when a checkpoint changed since ``clothgap eval``: its tables would be old numbers.
    """
    from eval.stage import stale_checkpoints

    run = Run(run.root.resolve(), run.config)       # relative links from report/, however the folder was named
    stale = stale_checkpoints(run)
    if stale:
        raise ConfigError(f"the eval results are stale: {', '.join(stale[:3])}{' ...' if len(stale) > 3 else ''} "
                          f"changed since they were computed; run `clothgap eval {run.root}` again first")
    sections = [("config", "Config", _section_config(run)), ("table3", "Table 3", _section_table3(run)),
                ("confusion", "Confusion", _section_confusion(run)), ("learning", "Learning", _section_learning(run)),
                ("frames", "Frames", _section_frames(run)), ("conv5", "conv5", _section_activations(run)),
                ("gap", "Domain gap", _section_gap(run)), ("ablations", "Recipes", _section_ablations(run)),
                ("measured", "Measured fabrics", _section_measured(run)),
                ("sim", "Sub-space", _section_sim_analysis(run)), ("real", "Real", _section_extra_tables(run))]
    sections = [s for s in sections if s[2]]
    nav = "".join(f'<a href="#{sid}">{_esc(title)}</a>' for sid, title, _ in sections)
    stamp = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    doc = (f'<!DOCTYPE html><html lang="en"><head><meta charset="utf-8"><title>clothgap report: '
           f"{_esc(run.config.name)}</title><style>{_CSS}</style></head><body><main>"
           f"<h1>clothgap: {_esc(run.config.name)}</h1>"
           f'<p class="meta">Run <code>{_esc(run.root.resolve())}</code>, written {stamp}. Rebuilds Yang, Liang, '
           "Lin, <i>Learning-based Cloth Material Recovery from Video</i> (ICCV 2017) as a sim-to-real gap study.</p>"
           f"<nav>{nav}</nav>{''.join(s[2] for s in sections)}</main></body></html>\n")
    path = run.report_dir / "report.html"
    atomic_write_text(path, doc)
    return path
