"""A combined render variant from the single variants that helped, chosen and reported on separate test clips.

The question (issue 15): what does one variant that randomises everything that helped buy? Choosing the
variants and measuring the result on the same test clips would count the luck of the choice as gain, so the
test sequences are cut in two by the parity of their sequence number (``SimConfig.sequence_of``: each
class's sequences fall in both halves, and a clip id is the same simulation under every variant):

- ``select``: on the **even** half, the paired accuracy gain of each training variant's models over the
  reference's, on the test variant. The variants that gained (point estimate > 0) are combined: the union
  of what each changes from ``paper``; where two set one key to different values the larger gain wins.
  Written as a normal variant file for ``$CLOTHGAP_VARIANTS_DIR``, with the selection in
  ``RUN/eval/combined-<name>.json``.
- ``report``: once the combined variant is rendered, trained and evaluated, on the **odd** half only:
  accuracy of the reference, of each chosen single variant, of the combined one, and the paired
  differences combined - reference and combined - best single (the single with the largest gain on the
  even half, so that it too is chosen without looking at the odd half).

Accuracy is per test sub-sequence (``train.clip_len`` frames: the whole clip in the paper preset) with the
seeds' predictions pooled, as in ``eval/results.csv``; intervals resample whole test sequences
(``eval.metrics``), seeded from the run's seed.
``scripts/combined_variant.py`` is the command.
"""

from __future__ import annotations

import json
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from clothgap import seeding
from clothgap.errors import ConfigError, InputError, MissingInputError
from clothgap.runs import Run, atomic_write_json, atomic_write_text, clip_index
from eval import metrics
from eval import predictions as preds
from eval.stage import only_windows, prediction_path, read_record, record_path, test_windows, variant_settings
from eval.trained import TrainedModel, checkpoint_sha256, finished_models
from render.variants import VARIANT_NAME, VARIANTS_DIR, RenderVariant

SELECTION, REPORT = "even", "odd"
UNIT = ("accuracy over 54 classes per test sub-sequence of train.clip_len frames (the whole clip in the paper "
        "preset), as eval/results.csv, the seeds' predictions pooled; intervals resample whole test sequences; "
        "differences are paired by clip id")
HALF_RULE = ("sequence number = clip index // number of classes (sim.config.SimConfig.sequence_of); the even "
             "half chooses the variants, the odd half reports them")
# The first line of every file select writes: it alone may be overwritten by select.
HEADER = "# Written by scripts/combined_variant.py select; run select again instead of editing this file.\n"


@dataclass(frozen=True)
class Question:
    """Models of one kind trained on several variants, tested on one variant, compared with a reference."""

    settings: tuple[str, ...]
    model: str
    test: str
    reference: str

    def as_dict(self) -> dict:
        return {"settings": list(self.settings), "model": self.model, "test_variant": self.test,
                "reference": self.reference}


def selection_path(run: Run, name: str) -> Path:
    return run.eval_dir / f"combined-{name}.json"


def report_path(run: Run, name: str, suffix: str) -> Path:
    return run.eval_dir / f"combined-{name}-report.{suffix}"


def half_of(run: Run, clip: str) -> str:
    """``"even"`` or ``"odd"``: the parity of the clip's sequence number."""
    try:
        index = clip_index(clip)
    except ValueError:
        raise InputError(f"test clip id {clip!r} is not c<index>: cannot tell its sequence number") from None
    return SELECTION if run.config.sim.sequence_of(index) % 2 == 0 else REPORT


# ------------------------------------------------------------------ what there is to compare

def default_settings(run: Run, model: str, test: str, reference: str) -> tuple[str, ...]:
    """The run's settings in which the reference's model has predictions on the test variant."""
    found = tuple(m.setting for m in finished_models(run) if m.variant == reference and m.model == model
                  and prediction_path(run, m, test).is_file())
    if not found:
        raise MissingInputError(f"no predictions of {reference}'s {model} model on {test!r} under "
                                f"{run.eval_dir / 'predictions'}: run `clothgap eval {run.root}` first (and check "
                                f"the names: --model, --test, --reference)")
    return tuple(dict.fromkeys(found))


def check_question(run: Run, q: Question) -> None:
    """One line naming what is unknown: a setting or model the run does not have."""
    cfg = run.config
    unknown = [s for s in q.settings if s not in cfg.sim.settings()]
    if unknown:
        raise ConfigError(f"unknown setting(s) {', '.join(unknown)}; the run has {', '.join(cfg.sim.settings())}")
    if q.model not in cfg.train.models:
        raise ConfigError(f"model {q.model!r} is not trained in {run.root}; its models: {', '.join(cfg.train.models)}")
    if q.reference == q.test:
        raise ConfigError(f"the reference and the test variant are both {q.test!r}: the reference must be a "
                          "training variant that is not the test look")


def finished(run: Run, q: Question, variant: str) -> dict[str, list[TrainedModel]]:
    """The finished ``q.model`` models (every seed) trained on ``variant``, per setting of ``q`` that has one."""
    out: dict[str, list[TrainedModel]] = {}
    for m in finished_models(run):
        if m.variant == variant and m.model == q.model and m.setting in q.settings:
            out.setdefault(m.setting, []).append(m)
    return out


def candidates(run: Run, q: Question, name: str) -> tuple[list[str], list[dict]]:
    """Training variants to weigh (a finished model in every setting of ``q``), and those left out and why.

    Neither the test variant (training on the test look is not a transfer) nor the combined variant itself
    (a second select after it was trained must choose the same) is a candidate."""
    trained = {m.variant for m in finished_models(run) if m.model == q.model}
    weighed, skipped = [], []
    if q.test in trained:
        skipped.append({"variant": q.test, "why": "the test variant: training on the test look is no transfer"})
    for v in sorted(trained - {q.reference, q.test, name}):
        missing = [s for s in q.settings if s not in finished(run, q, v)]
        if missing:
            skipped.append({"variant": v, "why": f"no finished {q.model} model for {', '.join(missing)}"})
        else:
            weighed.append(v)
    return weighed, skipped


def model_rows(run: Run, m: TrainedModel, test: str) -> pd.DataFrame:
    """Whether each of model ``m``'s eval predictions on the test variant's test sub-sequences is right.

    Only predictions whose record says they came from the checkpoint as it is now are used."""
    path = prediction_path(run, m, test)
    if not path.is_file():
        raise MissingInputError(f"no predictions {path}: run `clothgap eval {run.root}` first")
    record = read_record(path)
    if record is None or record.get("checkpoint_sha256") != checkpoint_sha256(m):
        raise MissingInputError(f"{path} is not known to come from {m.checkpoint} as it is now (its record "
                                f"{record_path(path).name} is missing or names another checkpoint): run "
                                f"`clothgap eval {run.root}` again")
    windows = test_windows(run, m.setting)
    frame = only_windows(preds.load(path), windows)
    frame = frame[frame["clip_id"].isin(windows)]
    return pd.DataFrame({"setting": m.setting, "clip_id": frame["clip_id"].to_numpy(),
                         "group": (m.setting + "/" + frame["clip_id"]).to_numpy(), "seed": m.seed,
                         "correct": metrics.correct(frame["class_index"], frame["pred"])})


def gather(run: Run, q: Question, variants: list[str], half: str) -> tuple[dict[str, pd.DataFrame], dict]:
    """Each variant's rows on the half's test clips that every one of them has predictions for, and the
    clips: per setting, those used and those left out (no prediction by some model)."""
    frames = {}
    for v in variants:
        models = finished(run, q, v)
        missing = [s for s in q.settings if s not in models]
        if missing:
            raise MissingInputError(f"variant {v!r} has no finished {q.model} model for {', '.join(missing)} "
                                    f"under {run.train_root}")
        frames[v] = pd.concat([model_rows(run, m, q.test) for s in q.settings for m in models[s]],
                              ignore_index=True)
    wanted = {f"{s}/{c}" for s in q.settings for c in test_windows(run, s) if half_of(run, c) == half}
    common = set.intersection(wanted, *(set(f["group"]) for f in frames.values()))
    if not common:
        raise MissingInputError(f"no test clip of the {half} half has predictions by every model compared "
                                f"({', '.join(variants)} on {q.test}) in {', '.join(q.settings)}")
    frames = {v: f[f["group"].isin(common)].reset_index(drop=True) for v, f in frames.items()}
    clips = {s: {"used": sorted(g.partition("/")[2] for g in common if g.partition("/")[0] == s),
                 "left_out": sorted(g.partition("/")[2] for g in wanted - common if g.partition("/")[0] == s)}
             for s in q.settings}
    return frames, clips


def changes_from_paper(run: Run, variant: str) -> dict:
    """What the variant was rendered with that differs from ``paper`` (its rendered meta, else its file)."""
    settings = variant_settings(run, variant)
    if not settings:
        raise ConfigError(f"cannot tell what variant {variant!r} changes: no rendered clip of it in {run.root} "
                          "and no variant file of that name")
    paper = RenderVariant().settings()
    return {k: v for k, v in settings.items() if k in paper and v != paper[k]}


# ------------------------------------------------------------------ estimates

def _rng(run: Run, *key: str) -> np.random.Generator:
    return seeding.rng(run.config.seed, 0, seeding.EVAL, "bootstrap", "combined", *key)


def _num(x: float) -> float | None:
    return round(float(x), 6) if np.isfinite(x) else None


def _est(e: metrics.Estimate) -> dict:
    return {"value": _num(e.value), "low": _num(e.low), "high": _num(e.high)}


def accuracy(run: Run, frame: pd.DataFrame, *key: str) -> dict:
    cfg = run.config.eval
    return _est(metrics.bootstrap_mean(frame["correct"], frame["group"], resamples=cfg.bootstrap,
                                       confidence=cfg.confidence, rng=_rng(run, "acc", *key)))


def difference(run: Run, a: pd.DataFrame, b: pd.DataFrame, *key: str) -> dict:
    """acc(a) - acc(b), paired by test sequence (the same clip id is the same simulation)."""
    cfg = run.config.eval
    return _est(metrics.bootstrap_mean_difference(a["correct"], a["group"], b["correct"], b["group"],
                                                  resamples=cfg.bootstrap, confidence=cfg.confidence,
                                                  rng=_rng(run, "difference", *key)))


def fmt_points(e: dict | None, sign: bool = True) -> str:
    """An estimate in percent (points): ``+3.1 [1.0, 5.2]``."""
    if not e or e["value"] is None:
        return "n/a"
    f = "+.1f" if sign else ".1f"
    lo = "n/a" if e["low"] is None else format(100 * e["low"], f)
    hi = "n/a" if e["high"] is None else format(100 * e["high"], f)
    return f"{format(100 * e['value'], f)} [{lo}, {hi}]"


# ------------------------------------------------------------------ select

def choose(gains: dict[str, float], changes: dict[str, dict]) -> tuple[list[str], list[dict]]:
    """The variants that gained, largest gain first, less any that sets a key another one with a larger
    gain set to a different value (ties go by name); and those conflicts."""
    union: dict[str, tuple[str, object]] = {}
    chosen, conflicts = [], []
    for v in sorted((v for v, g in gains.items() if g is not None and g > 0), key=lambda v: (-gains[v], v)):
        clash = sorted(k for k, value in changes[v].items() if k in union and union[k][1] != value)
        if clash:
            conflicts.append({"variant": v, "gain": gains[v], "keys": clash,
                              "kept": sorted({union[k][0] for k in clash}),
                              "why": "sets " + ", ".join(f"{k}={changes[v][k]!r} (kept {union[k][0]}: "
                                                         f"{union[k][1]!r})" for k in clash)})
            continue
        chosen.append(v)
        for k, value in changes[v].items():
            union.setdefault(k, (v, value))
    return chosen, conflicts


def check_name(run: Run, q: Question, name: str, variants_dir: Path) -> None:
    """The combined variant's name is free: a valid name, no built-in variant, not a file someone else wrote."""
    if not VARIANT_NAME.fullmatch(name):
        raise ConfigError(f"--name {name!r}: a variant name is letters, digits, '_' or '-', starting with a "
                          "letter or digit")
    if (VARIANTS_DIR / f"{name}.toml").is_file() or name in (q.reference, q.test):
        raise ConfigError(f"--name {name!r} is already a variant ({VARIANTS_DIR / name}.toml, or the "
                          "reference or test variant): choose another name")
    target = variants_dir / f"{name}.toml"
    if target.is_file() and not target.read_text(errors="replace").startswith(HEADER):
        raise ConfigError(f"{target} exists and was not written by select: choose another --name or move it")


def variant_text(name: str, description: str, settings: dict) -> str:
    """A variant file (``render.variants``) with the description and ``settings``, checked to read back."""
    lines = [HEADER.rstrip("\n"), f"description = {_toml(description)}"]
    lines += [f"{k} = {_toml(v)}" for k, v in settings.items()]
    text = "\n".join(lines) + "\n"
    data = tomllib.loads(text)
    back = RenderVariant(name=name, **{k: tuple(v) if isinstance(v, list) else v for k, v in data.items()})
    expected = RenderVariant(**{k: tuple(v) if isinstance(v, list) else v for k, v in settings.items()})
    if back.settings() != expected.settings():
        raise AssertionError(f"variant file for {name} does not read back: {back.settings()} != {expected.settings()}")
    return text


def _toml(value: object) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return json.dumps(value)    # a JSON string (\" \\ \n \uXXXX escapes) is a TOML basic string
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    raise TypeError(f"no TOML form for {value!r}")


def _candidate(run: Run, v: str, frames: dict[str, pd.DataFrame], q: Question, changes: dict) -> dict:
    """One candidate's entry: its changes, accuracy and gain over the reference (with intervals), per setting."""
    mine, ref = frames[v], frames[q.reference]
    per_setting = {s: _num(mine.loc[mine["setting"] == s, "correct"].mean()
                           - ref.loc[ref["setting"] == s, "correct"].mean()) for s in q.settings}
    return {"variant": v, "changes": changes, "seeds": sorted(int(s) for s in mine["seed"].unique()),
            "acc": accuracy(run, mine, SELECTION, q.test, v),
            "gain": difference(run, mine, ref, SELECTION, q.test, v, q.reference),
            "gain_per_setting": per_setting}


def select(run: Run, q: Question, name: str, variants_dir: Path) -> dict:
    """The selection on the even half: every candidate's gain, the variants chosen, the settings combined.

    Nothing is written (``write_selection`` does); ``settings`` is empty when nothing helped."""
    check_question(run, q)
    check_name(run, q, name, variants_dir)
    names, skipped = candidates(run, q, name)
    if not names:
        raise ConfigError(f"no training variant other than {q.reference} (and the test variant {q.test}) has a "
                          f"finished {q.model} model in {', '.join(q.settings)}: nothing to choose from")
    frames, clips = gather(run, q, [q.reference, *names], SELECTION)
    changes = {v: changes_from_paper(run, v) for v in names}
    entries = [_candidate(run, v, frames, q, changes[v]) for v in names]
    chosen, conflicts = choose({e["variant"]: e["gain"]["value"] for e in entries}, changes)
    for e in entries:
        e["helped"] = e["gain"]["value"] is not None and e["gain"]["value"] > 0
        e["chosen"] = e["variant"] in chosen
    union: dict = {}
    for c in chosen:            # chosen variants agree wherever they share a key (choose)
        union.update(changes[c])
    settings = {k: union[k] for k in RenderVariant().settings() if k in union}     # in the variant's field order
    return {"name": name, "question": q.as_dict(), "half": SELECTION, "half_rule": HALF_RULE, "unit": UNIT,
            "bootstrap": {"resamples": run.config.eval.bootstrap, "confidence": run.config.eval.confidence,
                          "seed": run.config.seed},
            "clips": clips, "reference_acc": accuracy(run, frames[q.reference], SELECTION, q.test, q.reference),
            "candidates": entries, "skipped": skipped, "conflicts": conflicts, "chosen": chosen,
            "best_single": chosen[0] if chosen else None,
            "checkpoints": _checkpoints(run, q, [q.reference, *names]),
            "settings": settings}


def _checkpoints(run: Run, q: Question, variants: list[str]) -> dict[str, list[str]]:
    """sha256 of each compared model's checkpoint, so that a later report can tell a model was retrained."""
    return {v: [f"{m.setting}/s{m.seed}:{checkpoint_sha256(m)}" for s in q.settings
                for m in finished(run, q, v).get(s, [])] for v in variants}


def description(record: dict, run: Run) -> str:
    q = record["question"]
    gain = {c["variant"]: c["gain"] for c in record["candidates"]}
    gains = ", ".join(f"{v} {fmt_points(gain[v])} points" for v in record["chosen"])
    return (f"Combined from the variants whose {q['model']} models beat {q['reference']} on {q['test_variant']} "
            f"(even test sequences of run {run.root.resolve().name}, {', '.join(q['settings'])}; accuracy gain per "
            f"sub-sequence [{100 * record['bootstrap']['confidence']:g}% interval]): {gains}.")


def write_selection(run: Run, record: dict, variants_dir: Path) -> tuple[Path, Path]:
    """The variant file and the selection record; refuses a name the run already rendered otherwise."""
    name, settings = record["name"], record["settings"]
    rendered = [s for s in run.config.sim.settings() if run.done_clips(run.render_dir(name, s))]
    if rendered and changes_from_paper(run, name) != settings:
        raise ConfigError(f"variant {name!r} is already rendered in {run.root} ({', '.join(rendered)}) with other "
                          f"settings than this selection's: choose another --name")
    variants_dir.mkdir(parents=True, exist_ok=True)
    target = (variants_dir / f"{name}.toml").resolve()
    text = variant_text(name, description(record, run), settings)
    record = {**record, "variant_file": str(target)}
    atomic_write_text(target, text)
    atomic_write_json(selection_path(run, name), record)
    return target, selection_path(run, name)


def selection_lines(record: dict) -> list[str]:
    """What select prints: the halves, each candidate's gain, conflicts, the chosen settings."""
    q = record["question"]
    n = sum(len(c["used"]) for c in record["clips"].values())
    lines = [f"selection half: even test sequences, {n} clips of {', '.join(q['settings'])}; {q['model']} models "
             f"tested on {q['test_variant']}",
             f"unit: {record['unit']}",
             f"{q['reference']} (reference): accuracy {fmt_points(record['reference_acc'], sign=False)} %"]
    for c in sorted(record["candidates"], key=lambda c: -(c["gain"]["value"] if c["gain"]["value"] is not None
                                                             else -np.inf)):
        verdict = "chosen" if c["chosen"] else ("helped, but conflicts" if c["helped"] else "did not help")
        lines.append(f"  {c['variant']:<20} gain {fmt_points(c['gain'])} points  {verdict}")
    lines += [f"  conflict: {c['variant']} left out: {c['why']}" for c in record["conflicts"]]
    lines += [f"  skipped: {s['variant']}: {s['why']}" for s in record["skipped"]]
    left = {s: c["left_out"] for s, c in record["clips"].items() if c["left_out"]}
    lines += [f"  left out (no prediction by some model): {s}: {', '.join(ids)}" for s, ids in left.items()]
    return lines


# ------------------------------------------------------------------ report

def read_selection(run: Run, name: str) -> dict:
    path = selection_path(run, name)
    if not path.is_file():
        raise MissingInputError(f"no selection {path}: run `python scripts/combined_variant.py select {run.root} "
                                f"--name {name}` first")
    try:
        return json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InputError(f"{path} is not valid JSON ({e}): run select again") from None


def report_question(record: dict, settings: tuple[str, ...] | None, model: str | None, test: str | None,
                    reference: str | None) -> Question:
    """The selection's question; a model, test or reference given must be the selection's (the halves and
    the choice belong to it). Settings may be a subset of the selection's."""
    q = record["question"]
    for flag, given, chosen in (("--model", model, q["model"]), ("--test", test, q["test_variant"]),
                                ("--reference", reference, q["reference"])):
        if given is not None and given != chosen:
            raise ConfigError(f"{flag} {given}: the selection {record['name']} was made with {flag} {chosen}")
    unknown = [s for s in settings or () if s not in q["settings"]]
    if unknown:
        raise ConfigError(f"--setting {', '.join(unknown)}: the selection was made on {', '.join(q['settings'])}")
    return Question(tuple(settings or q["settings"]), q["model"], q["test_variant"], q["reference"])


def check_combined(run: Run, q: Question, record: dict) -> None:
    """The combined variant was trained and rendered with the settings the selection wrote."""
    name = record["name"]
    models = finished(run, q, name)
    missing = [s for s in q.settings if s not in models]
    if missing:
        raise MissingInputError(
            f"the combined variant {name!r} is not trained yet ({', '.join(missing)}: no finished {q.model} under "
            f"{run.train_root}): CLOTHGAP_VARIANTS_DIR={Path(record['variant_file']).parent} clothgap pipeline "
            f"{run.root} --set render.variants={','.join(dict.fromkeys([*run.config.render.variants, name]))}")
    unevaluated = [prediction_path(run, m, q.test) for s in q.settings for m in models[s]
                   if not prediction_path(run, m, q.test).is_file()]
    if unevaluated:
        raise MissingInputError(f"the combined variant {name!r} is not evaluated yet (no {unevaluated[0]}): run "
                                f"`clothgap eval {run.root}`")
    rendered = changes_from_paper(run, name)
    if rendered != record["settings"]:
        raise ConfigError(f"variant {name!r} in {run.root} was rendered with other settings than the selection "
                          f"{selection_path(run, name)} wrote: {rendered}")


def report(run: Run, record: dict, q: Question) -> dict:
    """The odd half: accuracy of the reference, of each chosen single and of the combined variant; the
    paired differences combined - reference and combined - best single; the measured fabrics if there."""
    check_question(run, q)
    check_combined(run, q, record)
    name, best, chosen = record["name"], record["best_single"], record["chosen"]
    variants = [q.reference, *chosen, name]
    frames, clips = gather(run, q, variants, REPORT)
    ref = frames[q.reference]
    rows = []
    for v in variants:
        role = "reference" if v == q.reference else "combined" if v == name else (
            "chosen, best single" if v == best else "chosen")
        rows.append({"variant": v, "role": role, "acc": accuracy(run, frames[v], REPORT, q.test, v),
                     "minus_reference": None if v == q.reference else
                     difference(run, frames[v], ref, REPORT, q.test, v, q.reference),
                     "selection_gain": next((c["gain"] for c in record["candidates"] if c["variant"] == v), None)})
    now = _checkpoints(run, q, variants[:-1])
    changed = sorted(v for v in variants[:-1] if not set(now[v]) <= set(record["checkpoints"].get(v, [])))
    return {"name": name, "question": q.as_dict(), "half": REPORT, "half_rule": HALF_RULE, "unit": UNIT,
            "bootstrap": record["bootstrap"], "clips": clips, "rows": rows, "best_single": best,
            "combined_minus_reference": difference(run, frames[name], ref, REPORT, q.test, name, q.reference),
            "combined_minus_best_single": difference(run, frames[name], frames[best], REPORT, q.test, name, best),
            "models_changed_since_selection": changed, "settings": record["settings"],
            "measured": measured(run, q, variants, name, best)}


def measured(run: Run, q: Question, variants: list[str], name: str, best: str) -> dict:
    """Exact-class rate on the measured fabrics (``eval/measured.csv``), when every compared model is in it.

    That set never took part in the choice, so all of it counts; fabrics pair the models (seeds, settings
    pooled)."""
    path = run.eval_dir / "measured.csv"
    if not path.is_file():
        return {"included": False, "why": f"no {path} (clothgap eval measured {run.root})"}
    table = pd.read_csv(path)
    table = table[(table["model"] == q.model) & table["setting"].isin(q.settings)]
    missing = [v for v in variants if v not in set(table["train_variant"])]
    if missing:
        return {"included": False, "why": f"{path} has no {q.model} rows for {', '.join(missing)} "
                                          f"(clothgap eval measured {run.root})"}
    frames = {v: pd.DataFrame({"group": table.loc[table["train_variant"] == v, "fabric"].astype(str),
                               "correct": table.loc[table["train_variant"] == v, "exact"].astype(float)})
              for v in variants}
    common = set.intersection(*(set(f["group"]) for f in frames.values()))
    frames = {v: f[f["group"].isin(common)] for v, f in frames.items()}
    return {"included": True, "test_variant": sorted(set(table["test_variant"].astype(str))),
            "fabrics": sorted(common), "score": "exact class of the fabric (eval/measured.csv 'exact')",
            "rows": [{"variant": v, "exact": accuracy(run, frames[v], "measured", v)} for v in variants],
            "combined_minus_reference": difference(run, frames[name], frames[q.reference], "measured", name,
                                                   q.reference),
            "combined_minus_best_single": difference(run, frames[name], frames[best], "measured", name, best)}


def report_markdown(rep: dict, run: Run) -> str:
    q = rep["question"]
    n = sum(len(c["used"]) for c in rep["clips"].values())
    lines = [f"# Combined variant `{rep['name']}` (run `{run.root.resolve().name}`)", "",
             f"{q['model']} models tested on `{q['test_variant']}`, on the **odd** test sequences ({n} clips of "
             f"{', '.join(q['settings'])}); the variants were chosen on the even ones. {rep['unit'].capitalize()}; "
             f"{100 * rep['bootstrap']['confidence']:g}% intervals.", "",
             f"| trained on | role | accuracy (%) | minus {q['reference']} (points) | gain on the even half (points) |",
             "|---|---|---|---|---|"]
    for r in rep["rows"]:
        lines.append(f"| {r['variant']} | {r['role']} | {fmt_points(r['acc'], sign=False)} | "
                     f"{fmt_points(r['minus_reference']) if r['minus_reference'] else ''} | "
                     f"{fmt_points(r['selection_gain']) if r['selection_gain'] else ''} |")
    lines += ["", f"- combined minus {q['reference']}: {fmt_points(rep['combined_minus_reference'])} points",
              f"- combined minus the best single variant ({rep['best_single']}): "
              f"{fmt_points(rep['combined_minus_best_single'])} points",
              f"- combined settings: {', '.join(f'{k}={v!r}' for k, v in rep['settings'].items())}"]
    if rep["models_changed_since_selection"]:
        lines.append("- models retrained or added since the selection (their even-half gains were of other "
                     f"weights): {', '.join(rep['models_changed_since_selection'])}")
    m = rep["measured"]
    lines += ["", "## Measured fabrics", ""]
    if not m["included"]:
        return "\n".join(lines + [f"Not included: {m['why']}.", ""])
    lines += [f"Exact class rate over {len(m['fabrics'])} fabrics rendered in {', '.join(m['test_variant'])} "
              "(never used in the choice, so all of them count).", "", "| trained on | exact (%) |", "|---|---|"]
    lines += [f"| {r['variant']} | {fmt_points(r['exact'], sign=False)} |" for r in m["rows"]]
    lines += ["", f"- combined minus {q['reference']}: {fmt_points(m['combined_minus_reference'])} points",
              f"- combined minus {rep['best_single']}: {fmt_points(m['combined_minus_best_single'])} points", ""]
    return "\n".join(lines)


def write_report(run: Run, rep: dict) -> tuple[Path, Path, str]:
    text = report_markdown(rep, run)
    atomic_write_json(report_path(run, rep["name"], "json"), rep)
    atomic_write_text(report_path(run, rep["name"], "md"), text)
    return report_path(run, rep["name"], "json"), report_path(run, rep["name"], "md"), text
