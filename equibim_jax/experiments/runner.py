"""The experiment runner (``equibim experiment NAME``): the paper's tables as resumable runs.

An experiment is a JSON file (``tasks/experiments/NAME.json``) that lists *cells* and
*arms*. A cell is one training distribution (task + task options + demos + seed), one
policy (a preset: policy config, observation and action options, evaluation options), the
+EquiBim training settings, the evaluation settings and the evaluation distributions (the
training distribution, ``"train_dist"``, plus any shifted ones the cell names). An arm is
one way of training (:data:`ARMS`: ``baseline``, ``equibim``, ``mirror_augment``, ...). The
arms of a cell share the dataset, the normaliser and the seed, and are evaluated on the
same episode keys (paired), on the trained side and on the mirrored side of every
evaluation distribution.

Work is split into *units*, each keyed by a hash of everything that determines it:

* ``data``: the demos of a (task, options, demos, seed), ``units/data/<task>-<key>/``;
* ``train``: one arm's run on a dataset, ``units/runs/<task>-<arm>-<key>/``
  (``summary.json`` written last);
* ``eval``: all arms of a cell on one evaluation distribution,
  ``units/evals/<task>-<label>-<key>.json``.

A unit counts as done only when the manifest (``manifest.json`` in the output folder,
rewritten atomically after each unit) records it *and* its result file is there; a unit
cut short is redone (training resumes from its own checkpoint). Two experiments that share
units (``table2`` includes ``table1``'s cells) share them through their keys when they use
the same output folder. The manifest records each unit's wall time and size (steps,
episodes, demos); :func:`estimate` turns them into a wall-time estimate for another size.

Outputs per experiment, in ``OUT/NAME/``: ``results.json`` (every cell's summaries, sign
tests, unit keys, the paper's numbers), ``table.md`` and ``plot.png``
(:mod:`equibim_jax.experiments.tables`).
"""

from __future__ import annotations

import copy
import dataclasses
import datetime
import hashlib
import json
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from equibim_jax._io import atomic_write_json
from equibim_jax.config import ConfigError, EvalConfig, TaskConfig, config_from_dict, config_to_dict, find_config, load_config

__all__ = ["ARMS", "Cell", "Experiment", "Manifest", "load_experiment", "run_experiment", "estimate", "merge_previous",
           "expert_rollout", "random_rollout", "unit_key", "experiment_path", "DEFAULT_OUT"]

DEFAULT_OUT = "results/experiments"
"""Default output folder (``--quick`` runs use ``results/experiments-quick``)."""

EXPERIMENT_DIR = "tasks/experiments"


def _baseline(tc):
    return dataclasses.replace(tc, sym_weight=0.0, sym_stop_gradient=False, sym_warmup_steps=0,
                               sym_start_step=0, sym_batch_size=None, mirror_augment=False)


ARMS: dict[str, tuple[str, Callable]] = {
    "baseline": ("plain behaviour cloning (no L_sym, no augmentation)", _baseline),
    "equibim": ("+EquiBim: L_sym as the experiment's train settings give it",
                lambda tc: dataclasses.replace(tc, mirror_augment=False)),
    "mirror_augment": ("mirror data augmentation, no L_sym",
                       lambda tc: dataclasses.replace(_baseline(tc), mirror_augment=True)),
    "equibim+augment": ("L_sym and mirror augmentation", lambda tc: dataclasses.replace(tc, mirror_augment=True)),
    "equibim_public": ("L_sym in the public code's form: squared error, stop-gradient target",
                       lambda tc: dataclasses.replace(tc, sym_norm="mse", sym_stop_gradient=True,
                                                      mirror_augment=False)),
    "equibim_paper": ("L_sym in the paper's written form: norm, gradients through both branches",
                      lambda tc: dataclasses.replace(tc, sym_norm="l2", sym_stop_gradient=False,
                                                     mirror_augment=False)),
}
"""Arm name -> (description, ``f(TrainConfig) -> TrainConfig``) applied to the cell's
+EquiBim train settings."""

VIEWS = ("average", "per_task", "per_cell")
_TOP_KEYS = {"name", "description", "seed", "demos", "arms", "policies", "train", "eval", "tasks",
             "cells", "grid", "include", "view", "quick", "paper", "full_size_estimate"}
_CELL_KEYS = {"name", "task", "options", "policy", "demos", "train", "eval", "shifts", "eval_options"}


@dataclasses.dataclass(frozen=True)
class Cell:
    """One training distribution and policy, trained by every arm of the experiment.

    Attributes:
      name: unique within the experiment (``"task/preset"`` by default).
      task: the training distribution (task, options incl. ``obs``/``action``).
      preset: the policy preset's name; policy: its resolved config.
      demos, seed: dataset size and seed (of generation, training and parameter init).
      train: the +EquiBim train settings (arms derive theirs from it, :data:`ARMS`).
      eval: evaluation settings (episodes per side, seed, temporal ensembling).
      evals: ``((label, env options), ...)``: ``"train_dist"`` first, then the shifts.
    """

    name: str
    task: TaskConfig
    preset: str
    policy: Any
    demos: int
    seed: int
    train: Any
    eval: EvalConfig
    evals: tuple

    def arm_config(self, arm: str):
        """The train config of ``arm`` on this cell (seed included)."""
        return dataclasses.replace(ARMS[arm][1](self.train), seed=self.seed)


@dataclasses.dataclass(frozen=True)
class Experiment:
    """A parsed experiment config: ``cells`` x ``arms``, how to tabulate them (``view``), the
    paper's numbers (``paper``), and whether it is the ``--quick`` size."""

    name: str
    description: str
    arms: tuple
    cells: tuple
    view: str
    paper: dict
    quick: bool
    source: str
    full_size_estimate: dict


def experiment_path(name: str) -> Path:
    """``tasks/experiments/NAME.json``, or ``name`` itself if it is a JSON file path."""
    if name.endswith(".json") or "/" in name:
        return find_config(name)
    return find_config(f"{EXPERIMENT_DIR}/{name}.json")


def _merge(base: Mapping, over: Mapping) -> dict:
    """Deep merge of two JSON dicts (``over`` wins; nested dicts merged)."""
    out = copy.deepcopy(dict(base))
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, Mapping) and isinstance(out.get(k), Mapping) else copy.deepcopy(v)
    return out


def _read(path: Path) -> dict:
    data = load_config(path)  # a JSON object, or a ConfigError naming the file
    unknown = set(data) - _TOP_KEYS
    if unknown:
        raise ConfigError(f"{path}: unknown experiment keys {sorted(unknown)}; valid: {sorted(_TOP_KEYS)}")
    return data


def _raw_cells(data: dict, path: Path, seen: tuple = ()) -> list[dict]:
    """The cell dicts of an experiment file: its ``include``-d experiments' cells (with
    their presets and defaults resolved), its ``grid`` (tasks x presets) and ``cells``."""
    cells = []
    inc = data.get("include")
    if inc is not None:
        ip = experiment_path(inc)
        if ip.resolve() in seen:
            raise ConfigError(f"{path}: include cycle through {ip}")
        idata = _with_included_defaults(_read(ip), ip, seen + (path.resolve(),))
        for c in _raw_cells(idata, ip, seen + (path.resolve(),)):
            cells.append(_resolve_defaults(c, idata, ip))
    grid = data.get("grid")
    if grid is not None:
        if not isinstance(grid, Mapping) or set(grid) - {"tasks", "policies"}:
            raise ConfigError(f"{path}: 'grid' must be {{'tasks': [...], 'policies': [...]}}")
        for t in grid.get("tasks", []):
            t = {"task": t} if isinstance(t, str) else dict(t)
            for p in grid.get("policies", []):
                cells.append({**t, "policy": p, "_local": True})
    for c in data.get("cells", []):
        if not isinstance(c, Mapping):
            raise ConfigError(f"{path}: every cell must be a JSON object, got {c!r}")
        cells.append({**c, "_local": True})
    return cells


_BY_NAME = ("policies", "tasks")
_WHOLE = ("seed", "demos", "train", "eval", "quick")


def _with_included_defaults(data: dict, path: Path, seen: tuple = ()) -> dict:
    """``data`` with what its own cells resolve against taken from its ``include`` chain
    where the file does not give it: policy presets and per-task defaults by name (a local
    entry replaces the included one of that name), ``seed``, ``demos``, ``train`` and
    ``eval`` as a whole, and the ``quick`` sizes key by key (a local key wins; the included
    ``quick.cells`` never applies). An including experiment's cells therefore use the
    included experiment's presets and quick sizes, not copies that can fall out of date."""
    inc = data.get("include")
    if inc is None:
        return data
    ip = experiment_path(inc)
    if ip.resolve() in seen or ip.resolve() == path.resolve():
        raise ConfigError(f"{path}: include cycle through {ip}")
    base = _with_included_defaults(_read(ip), ip, seen + (path.resolve(),))
    out = dict(data)
    for k in _BY_NAME:
        if k in base:
            out[k] = {**base[k], **data.get(k, {})}
    for k in _WHOLE:
        if k not in data and k in base:
            out[k] = base[k]
    if "quick" in data and "quick" in base:  # the included quick sizes, key by key; its cells stay its own
        out["quick"] = {**{k: v for k, v in base["quick"].items() if k != "cells"}, **data["quick"]}
    return out


def _resolve_defaults(c: dict, data: dict, path: Path) -> dict:
    """A cell dict with its file's presets and defaults folded in (so it no longer depends
    on the file it came from)."""
    if not c.pop("_local", False):
        return c
    unknown = set(c) - _CELL_KEYS
    if unknown:
        raise ConfigError(f"{path}: cell {c.get('name', c.get('task'))!r}: unknown keys {sorted(unknown)}; "
                          f"valid: {sorted(_CELL_KEYS)}")
    if "task" not in c or "policy" not in c:
        raise ConfigError(f"{path}: every cell needs a 'task' and a 'policy' (preset name), got {c}")
    presets = data.get("policies", {})
    pname = c["policy"]
    if not isinstance(pname, str) or pname not in presets:
        raise ConfigError(f"{path}: unknown policy preset {pname!r}; the file defines {sorted(presets)}")
    preset = presets[pname]
    bad = set(preset) - {"policy", "options", "eval", "train"}
    if bad:
        raise ConfigError(f"{path}: policy preset {pname!r}: unknown keys {sorted(bad)}; "
                          "valid: ['eval', 'options', 'policy', 'train']")
    task = c["task"]
    topts = data.get("tasks", {}).get(task, {}) if isinstance(data.get("tasks"), Mapping) else {}
    return {
        "name": c.get("name", f"{task}/{pname}"),
        "task": task,
        "preset": pname,
        "options": _merge(_merge(preset.get("options", {}), topts.get("options", {})), c.get("options", {})),
        "policy": copy.deepcopy(preset.get("policy", {})),
        "demos": c.get("demos", topts.get("demos", data.get("demos", 50))),
        "seed": data.get("seed", 0),
        "train": _merge(_merge(data.get("train", {}), preset.get("train", {})), c.get("train", {})),
        "eval": _merge(_merge(data.get("eval", {}), preset.get("eval", {})), c.get("eval", {})),
        "shifts": _merge(topts.get("shifts", {}), c.get("shifts", {})),
        "eval_options": _merge(topts.get("eval_options", {}), c.get("eval_options", {})),
        "quick": data.get("quick", {}),
    }


def _check_options(task: str, options: Mapping, where: str) -> None:
    from equibim_jax.tasks import task_names, task_options

    if task not in task_names():
        raise ConfigError(f"{where}: unknown task {task!r}; valid tasks: {task_names()}")
    valid = task_options(task)
    bad = sorted(k for k in options if k not in valid)
    if bad:
        raise ConfigError(f"{where}: unknown options {bad} of task {task!r}; valid: {list(valid)}")


def _build_cell(c: dict, quick: bool, path: Path):
    from equibim_jax.policies.base import PolicyConfig
    from equibim_jax.training.train_step import TrainConfig

    where = f"{path}: cell {c['name']!r}"
    if quick:
        q = c["quick"]
        bad = set(q) - {"demos", "train", "eval", "options", "policies", "cells"}
        if bad:
            raise ConfigError(f"{path}: 'quick': unknown keys {sorted(bad)}")
        c = {**c, "demos": q.get("demos", c["demos"]), "train": _merge(c["train"], q.get("train", {})),
             "eval": _merge(c["eval"], q.get("eval", {})),
             "options": _merge(c["options"], q.get("options", {})),
             "policy": _merge(c["policy"], q.get("policies", {}).get(c["preset"], {}))}
    _check_options(c["task"], c["options"], where)
    try:
        policy = config_from_dict(PolicyConfig, c["policy"])
        train = config_from_dict(TrainConfig, c["train"])
        ev = config_from_dict(EvalConfig, c["eval"])
    except ConfigError as e:
        raise ConfigError(f"{where}: {e}") from None
    if not isinstance(c["demos"], int) or c["demos"] < 1:
        raise ConfigError(f"{where}: demos must be an integer >= 1, got {c['demos']!r}")
    if not train.sym_weight > 0:
        raise ConfigError(f"{where}: train.sym_weight must be > 0 (the +EquiBim arms need L_sym)")
    base_eval = _merge(c["options"], c["eval_options"])
    _check_options(c["task"], base_eval, f"{where} eval_options")
    evals = [("train_dist", base_eval)]
    for label, sopts in c["shifts"].items():
        if label == "train_dist" or not isinstance(sopts, Mapping):
            raise ConfigError(f"{where}: shift {label!r} must be a label (not 'train_dist') -> options object")
        sopts = _merge(base_eval, sopts)
        _check_options(c["task"], sopts, f"{where} shift {label!r}")
        evals.append((label, sopts))
    return Cell(c["name"], TaskConfig(c["task"], c["options"]), c["preset"], policy, c["demos"], int(c["seed"]),
                train, ev, tuple(evals))


def load_experiment(name: str, quick: bool = False, only: tuple[str, ...] | None = None) -> Experiment:
    """Read and check an experiment config (``tasks/experiments/NAME.json`` or a path).

    ``quick`` applies the file's ``quick`` overrides (sizes, and ``quick.cells``: the cells
    a quick run keeps, all if absent). ``only`` keeps the cells whose name equals or starts
    with one of the given strings (``"click_bell"`` matches ``"click_bell/dp3_joint"``).

    Raises:
      ConfigError: unknown keys, task, task option, policy preset or field, or arm; a cell
        name used twice; ``only`` matching nothing.
    """
    path = experiment_path(name)
    data = _read(path)
    arms = tuple(data.get("arms", ("baseline", "equibim")))
    bad = [a for a in arms if a not in ARMS]
    if bad:
        raise ConfigError(f"{path}: unknown arms {bad}; valid: {sorted(ARMS)}")
    if "baseline" not in arms:
        raise ConfigError(f"{path}: arms must include 'baseline' (the sign tests compare against it)")
    view = data.get("view", "per_cell")
    if view not in VIEWS:
        raise ConfigError(f"{path}: unknown view {view!r}; valid: {VIEWS}")
    local = _with_included_defaults(data, path)
    raws = [_resolve_defaults(c, local, path) for c in _raw_cells(data, path)]
    if not raws:
        raise ConfigError(f"{path}: no cells (give 'cells', 'grid' or 'include')")
    names = [c["name"] for c in raws]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ConfigError(f"{path}: cell names used twice: {dup}")
    if quick and data.get("quick", {}).get("cells"):
        keep = data["quick"]["cells"]
        missing = [k for k in keep if k not in names]
        if missing:
            raise ConfigError(f"{path}: quick.cells names unknown cells {missing}; cells: {names}")
        raws = [c for c in raws if c["name"] in keep]
    if only:
        raws = [c for c in raws if any(c["name"] == o or c["name"].startswith(o) for o in only)]
        if not raws:
            raise ConfigError(f"{path}: --only {list(only)} matches no cell; cells: {names}")
    cells = tuple(_build_cell(c, quick, path) for c in raws)
    return Experiment(data.get("name", path.stem), data.get("description", ""), arms, cells, view,
                      data.get("paper", {}), quick, str(path), data.get("full_size_estimate", {}))


# ----------------------------------------------------------------------------- units

def unit_key(kind: str, spec: Any) -> str:
    """A 12-hex-digit key of a unit: hash of its kind and its JSON-able spec."""
    blob = json.dumps({"kind": kind, "spec": config_to_dict(spec)}, sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:12]


class Manifest:
    """The record of finished units, ``{"units": {key: record}}`` in one JSON file,
    rewritten atomically after every change. A record holds ``kind``, ``path`` (relative
    to the output folder), ``finished`` (UTC ISO time), ``wall_s`` and the unit's sizes."""

    def __init__(self, root: Path):
        self.root = Path(root)
        self.path = self.root / "manifest.json"
        self.units: dict = {}
        if self.path.exists():
            try:
                self.units = json.loads(self.path.read_text()).get("units", {})
            except (json.JSONDecodeError, AttributeError):
                raise ConfigError(f"{self.path} is not a manifest (move it away)") from None

    def done(self, key: str) -> bool:
        """Recorded and its result file present."""
        rec = self.units.get(key)
        return bool(rec) and (self.root / rec["path"]).exists()

    def record(self, key: str, **rec) -> None:
        rec["finished"] = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
        self.units[key] = rec
        atomic_write_json(self.path, {"units": self.units})


def _strip(summary: dict) -> dict:
    return {k: v for k, v in summary.items() if k not in ("batch_s",)}


def _data_unit(cell: Cell, root: Path, manifest: Manifest, progress: bool, envs: dict):
    from equibim_jax.data.dataset import load
    from equibim_jax.data.generate import generate_dataset

    gen = _gen_task(cell.task)
    key = unit_key("data", {"task": gen, "demos": cell.demos, "seed": cell.seed})
    rel = f"units/data/{cell.task.name}-{key}/demos.zarr"
    space = cell.task.options.get("action", "joint")
    if manifest.done(key):
        return key, load(root / rel).in_action_space(space)
    env = _env(gen, envs)
    t0 = time.perf_counter()
    demos, stats = generate_dataset(env, root / rel, cell.demos, seed=cell.seed, overwrite=True, progress=progress)
    manifest.record(key, kind="data", path=rel, cell=cell.name, task=cell.task.name, demos=cell.demos,
                    wall_s=time.perf_counter() - t0,
                    stats={k: v for k, v in stats.items() if isinstance(v, (int, float, str))})
    return key, demos.in_action_space(space)


def _gen_task(task: TaskConfig) -> TaskConfig:
    """The task config demos are generated in: the scripted experts emit joint actions, so
    an ``action="ee"`` cell's demos come from the joint-action env (they record the same
    actions in the end-effector space too, ``Demos.action_ee``) and are trained on in
    that space."""
    return TaskConfig(task.name, {**task.options, "action": "joint"})


def _norm_rule(cell: Cell) -> dict:
    """The part of a train unit's key that names the normaliser's rule, where the cell has
    end-effector rotation channels (``ee`` observed or ``action="ee"``): they are left
    unscaled (``training.run.rotation_channels``). Runs trained before that rule min-max
    scaled them; their keys, without this entry, are not reused for it. Cells without such
    channels keep their keys."""
    ee = "ee" in tuple(cell.policy.obs_keys) or cell.task.options.get("action", "joint") == "ee"
    return {"normalizer": {"ee_rotation": "unscaled"}} if ee else {}


def _steady_step_s(s: dict, steps: int, k: int) -> float | None:
    """Seconds per train step after the first dispatch (which includes compiling), or
    over all steps when there was one dispatch; None when no step ran."""
    if steps <= 0:
        return None
    first = s.get("first_dispatch_s_incl_compile")
    if first is not None and steps > k:
        return (s["train_s"] - first) / (steps - k)
    return s["train_s"] / steps


def _env(task: TaskConfig, envs: dict):
    h = unit_key("env", task)
    if h not in envs:
        envs[h] = task.make_env()
    return envs[h]


def run_cell(cell: Cell, arms: tuple, root: Path, manifest: Manifest, progress: bool = True,
             envs: dict | None = None) -> dict:
    """Every unit of one cell (skipping the finished ones) and its summary:
    ``{"evals": {label: {arm: {side: summary}}}, "sign_tests": {label: {arm: {side: test}}},
    "units": {...}, "train": {arm: {steps, final losses}}}``."""
    from equibim_jax.evaluation.evaluate import evaluate_policies
    from equibim_jax.evaluation.stats import paired_sign_test
    from equibim_jax.training import run as trun
    from equibim_jax.training.checkpoint import latest_step

    envs = {} if envs is None else envs
    dkey, demos = _data_unit(cell, root, manifest, progress, envs)
    normalizer = None
    run_keys, run_dirs, train_info, pending = {}, {}, {}, {}
    for arm in arms:
        tc = cell.arm_config(arm)
        rkey = unit_key("train", {"data": dkey, "policy": cell.policy, "train": tc, **_norm_rule(cell)})
        rel = f"units/runs/{cell.task.name}-{rkey}"  # arms with equal configs share it
        run_keys[arm], run_dirs[arm] = rkey, root / rel
        if (not manifest.done(rkey) or not (root / rel / "summary.json").exists()) and rkey not in pending:
            pending[rkey] = (arm, tc, rel)
    # the unfinished runs of the cell train together (one program), grouped by the step
    # they resume from; each is recorded as its own unit with its share of the time
    groups: dict = {}
    for rkey, (arm, tc, rel) in pending.items():
        groups.setdefault((latest_step(root / rel / "ckpt"), tc.total_steps, tc.steps_per_dispatch), []).append(rkey)
    for group in groups.values():
        env = _env(cell.task, envs)
        if normalizer is None:  # one normaliser for every arm of the cell
            normalizer = trun.prepare_data(demos, env, cell.policy).normalizer
        t0 = time.perf_counter()
        sums = trun.train_together(demos, {pending[k][0]: (root / pending[k][2], pending[k][1]) for k in group},
                                   cell.policy, env=env, normalizer=normalizer, progress=progress,
                                   desc=f"{cell.name} " + " + ".join(pending[k][0] for k in group))
        wall = time.perf_counter() - t0
        for rkey in group:
            arm, tc, rel = pending[rkey]
            s = sums[arm]
            if not s.get("final") and (root / rel / "train.jsonl").exists():  # resumed at its end
                rows = trun.read_log(root / rel / "train.jsonl")
                s["final"] = rows[-1] if rows else {}
            share = wall / len(group)
            s = {**s, "wall_s": wall, "wall_s_share": share}
            atomic_write_json(root / rel / "summary.json", s)
            done_steps = s["steps"] - s["resumed_from"]
            per_step = _steady_step_s(s, done_steps, tc.steps_per_dispatch)
            manifest.record(rkey, kind="train", path=f"{rel}/summary.json", cell=cell.name, arm=arm,
                            task=cell.task.name, policy=cell.preset, steps=done_steps,
                            total_steps=tc.total_steps, wall_s=share, trained_with=len(group),
                            s_per_step=None if per_step is None else per_step / len(group))
    for arm in arms:
        s = json.loads((run_dirs[arm] / "summary.json").read_text())
        train_info[arm] = {"steps": s["steps"], "final": s.get("final", {})}
    evals, tests, eval_keys = {}, {}, {}
    for label, opts in cell.evals:
        ekey = unit_key("eval", {"runs": run_keys, "eval": cell.eval, "task": cell.task.name, "options": opts})
        rel = f"units/evals/{cell.task.name}-{label}-{ekey}.json"
        eval_keys[label] = ekey
        if not manifest.done(ekey):
            runs = {arm: trun.load_run(run_dirs[arm]) for arm in arms}
            first = runs[arms[0]]
            env = _env(TaskConfig(cell.task.name, opts), envs)
            t0 = time.perf_counter()
            ev = evaluate_policies(env, first.policy, first.normalizer,
                                   {arm: r.state.ema_params for arm, r in runs.items()}, cell.eval,
                                   progress=progress)
            wall = time.perf_counter() - t0
            atomic_write_json(root / rel, {arm: {side: _strip(v) for side, v in sides.items()}
                                           for arm, sides in ev.items()})
            manifest.record(ekey, kind="eval", path=rel, cell=cell.name, label=label, task=cell.task.name,
                            policy=cell.preset, arms=len(arms), episodes=cell.eval.episodes,
                            episode_length=int(env.config.episode_length), wall_s=wall)
        ev = json.loads((root / rel).read_text())
        evals[label] = ev
        tests[label] = {arm: {side: paired_sign_test(ev["baseline"][side]["per_episode"], ev[arm][side]["per_episode"])
                              for side in ev[arm]}
                        for arm in arms if arm != "baseline"}
    return {"task": cell.task.name, "preset": cell.preset, "options": cell.task.options,
            "evals": evals, "sign_tests": tests, "train": train_info,
            "units": {"data": dkey, "train": run_keys, "eval": eval_keys}}


def run_experiment(exp: Experiment, out_dir: str | Path | None = None, progress: bool = True,
                   command: str = "") -> dict:
    """Run (or resume) every cell of ``exp``; writes ``OUT/NAME/{results.json, table.md,
    plot.png}`` and returns the results dict. ``out_dir`` defaults to :data:`DEFAULT_OUT`
    (``results/experiments-quick`` for a quick experiment). The cells of an existing
    ``OUT/NAME/results.json`` that this invocation did not run stay in the table when their
    config is unchanged (:func:`merge_previous`); each cell records the ``command`` that ran
    it, and ``commands`` lists those of the cells in the table."""
    from tqdm.auto import tqdm

    from equibim_jax.experiments import tables

    root = Path(out_dir if out_dir is not None else (DEFAULT_OUT + "-quick" if exp.quick else DEFAULT_OUT))
    root.mkdir(parents=True, exist_ok=True)
    manifest = Manifest(root)
    out = root / exp.name

    def previous():  # read after the cells ran: the table as it is now, not as it was at the start
        return _read_results(out / "results.json")

    previous()  # a broken results.json stops the run before any work
    for inc in _included_names(experiment_path(exp.source)):
        _read_results(root / inc / "results.json")
    t0 = time.perf_counter()
    cells, envs = {}, {}
    for cell in tqdm(exp.cells, desc=f"experiment {exp.name}", unit="cell", disable=not progress):
        cells[cell.name] = run_cell(cell, exp.arms, root, manifest, progress=progress, envs=envs)
        envs.clear()  # envs are cheap to rebuild and hold device memory
    prev = previous()
    configs = {c.name: _cell_config(c) for c in exp.cells}
    full = load_experiment(exp.source, quick=exp.quick)
    full_cfg = {c.name: _cell_config(c) for c in full.cells}
    # The previous table of this experiment, then those of the experiments it includes
    # (``table2`` shows ``table1``'s cells): a cell comes from the first that holds it.
    kept = {}
    sources = [(exp.name, prev)] + [(inc, _read_results(root / inc / "results.json"))
                                    for inc in _included_names(experiment_path(exp.source))]
    for name, old in sources:
        if old is None:
            continue
        more = merge_previous(old, name, exp.quick, list(exp.arms), full_cfg, set(cells) | set(kept))
        legacy = "commands" not in old  # one command made the whole old table
        for v in more.values():  # cells from before per-cell commands were recorded; else unknown
            v["cell"].setdefault("command", old.get("command", "") if legacy else "")
        kept.update(more)
    order = [c.name for c in full.cells]
    for c in cells.values():
        c["command"] = command
    all_cells = {**{k: v["cell"] for k, v in kept.items()}, **cells}
    all_cells = {n: all_cells[n] for n in order if n in all_cells}
    configs = {**{k: v["config"] for k, v in kept.items()}, **configs}
    commands = list(dict.fromkeys(c["command"] for c in all_cells.values() if c.get("command")))
    results = {"experiment": exp.name, "description": exp.description, "quick": exp.quick,
               "arms": list(exp.arms), "view": exp.view, "source": exp.source, "command": command,
               "commands": commands,
               "wall_time_s": time.perf_counter() - t0, "cells": all_cells, "paper": exp.paper,
               "full_size_estimate": exp.full_size_estimate,
               "configs": {n: configs[n] for n in all_cells}}
    results["summary"] = tables.summarize(results)
    atomic_write_json(out / "results.json", results)
    (out / "table.md").parent.mkdir(parents=True, exist_ok=True)
    from equibim_jax._io import atomic_write_bytes

    atomic_write_bytes(out / "table.md", tables.markdown(results).encode())
    tables.plot(results, out / "plot.png")
    return results


def _read_results(path: Path) -> dict | None:
    """A ``results.json`` as a dict, ``None`` if it does not exist.

    Raises:
      ConfigError: the file is not valid JSON.
    """
    if not path.exists():
        return None
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError:
        raise ConfigError(f"{path} is not valid JSON (move it away)") from None


def _included_names(path: Path) -> list[str]:
    """Names of the experiments an experiment file includes, nearest first (``include``
    chains are followed; cycles are caught by :func:`load_experiment`)."""
    names, seen = [], {path.resolve()}
    inc = _read(path).get("include")
    while inc is not None:
        ip = experiment_path(inc)
        if ip.resolve() in seen:
            break
        seen.add(ip.resolve())
        idata = _read(ip)
        names.append(idata.get("name", ip.stem))
        inc = idata.get("include")
    return names


def _cell_config(c: Cell) -> dict:
    """The JSON form of everything that determines a cell's results."""
    return json.loads(json.dumps({"task": config_to_dict(c.task), "policy": config_to_dict(c.policy),
                                  "demos": c.demos, "seed": c.seed, "train": config_to_dict(c.train),
                                  "eval": config_to_dict(c.eval), "evals": [list(e) for e in c.evals],
                                  **_norm_rule(c)},
                                 default=str))


def merge_previous(prev: Mapping, name: str, quick: bool, arms: list, configs: Mapping,
                   ran: set) -> dict:
    """The cells of a previous ``results.json`` (``prev``) that a new invocation keeps:
    ``{cell name: {"cell": ..., "config": ...}}``.

    A table can be built over several invocations (``--only`` a few cells at a time, or
    on another machine whose unit files are gone): a previous cell is kept when this
    invocation did not run it (``ran``), ``prev`` is the same experiment at the same size
    with the same arms, and the cell's recorded config equals its config in the current
    experiment file (``configs``, JSON form); a cell whose config has changed is dropped,
    never mixed in.
    """
    if prev.get("experiment") != name or bool(prev.get("quick")) != bool(quick) or list(prev.get("arms", [])) != list(arms):
        return {}
    old_cfg = prev.get("configs", {})
    return {n: {"cell": c, "config": old_cfg[n]} for n, c in prev.get("cells", {}).items()
            if n not in ran and n in configs and n in old_cfg
            and json.loads(json.dumps(old_cfg[n], default=str)) == configs[n]}


def estimate(full: Experiment, manifest: Manifest) -> dict:
    """Extrapolated wall time of ``full`` from the measured units in ``manifest``.

    Per unit of ``full``: a data unit takes (measured seconds per demo) x demos; a train
    unit (measured seconds per step) x total steps; an eval unit (measured seconds per
    episode-step per arm) x episodes x 2 sides x episode length x arms. Rates come from
    the manifest's records of the same task and policy preset (else the same preset, else
    the same kind). They are measured at whatever size those units ran (a ``--quick`` run's
    smaller models and images are faster per step), so the result is an extrapolation.

    Returns:
      ``{"total_s", "by_kind": {kind: s}, "missing": [unit descriptions without a rate]}``.
    """
    recs = list(manifest.units.values())

    def rate(kind, task, preset, f):
        for match in (lambda r: r.get("task") == task and r.get("policy", preset) == preset,
                      lambda r: r.get("policy", preset) == preset, lambda r: True):
            vals = [f(r) for r in recs if r.get("kind") == kind and match(r) and f(r) is not None]
            if vals:
                return float(np.median(vals))
        return None

    by_kind = {"data": 0.0, "train": 0.0, "eval": 0.0}
    missing = []
    seen = set()
    for c in full.cells:
        dk = unit_key("data", {"task": _gen_task(c.task), "demos": c.demos, "seed": c.seed})
        if dk not in seen:
            seen.add(dk)
            r = rate("data", c.task.name, None, lambda r: r["wall_s"] / r["demos"] if r.get("demos") else None)
            by_kind["data"] += r * c.demos if r else 0.0
            missing += [] if r else [f"data {c.name}"]
        for arm in full.arms:
            tc = c.arm_config(arm)
            rk = unit_key("train", {"data": dk, "policy": c.policy, "train": tc})
            if rk in seen:
                continue
            seen.add(rk)
            r = rate("train", c.task.name, c.preset, lambda r: r.get("s_per_step"))
            by_kind["train"] += r * tc.total_steps if r else 0.0
            missing += [] if r else [f"train {c.name} {arm}"]
        for label, _ in c.evals:
            r = rate("eval", c.task.name, c.preset,
                     lambda r: r["wall_s"] / (2 * r["episodes"] * r["episode_length"] * r["arms"])
                     if r.get("episode_length") else None)
            length = c.task.options.get("episode_length")
            if length is None:
                from equibim_jax.tasks import task_entry

                length = task_entry(c.task.name).step_limit
            by_kind["eval"] += r * 2 * c.eval.episodes * length * len(full.arms) if r else 0.0
            missing += [] if r else [f"eval {c.name} {label}"]
    return {"total_s": sum(by_kind.values()), "by_kind": by_kind, "missing": missing}


# ----------------------------------------------------------------------------- reference controllers

def expert_rollout(env) -> Callable:
    """The task's scripted expert as a closed-loop controller with a policy rollout's
    interface: ``rollout(params, key, mirrored) -> {"success": [] bool, "success_t": [T]
    bool, "nan_actions": [] int32}`` (``params`` unused), for
    :func:`~equibim_jax.evaluation.rollout.evaluate_sides`. The mirrored side starts from
    ``env.mirror_state`` of the same reset, as a policy's does."""
    import jax
    import jax.numpy as jnp

    from equibim_jax.experts import make_rollout
    from equibim_jax.tasks import make_expert

    run_from = make_rollout(env, make_expert(env), obs=False).from_state

    def rollout(params, key, mirrored=False):
        s0 = env.reset(key)
        s0 = jax.lax.cond(mirrored, env.mirror_state, lambda s: s, s0)
        final, traj = run_from(s0)
        return {"success": final.info["success"], "success_t": traj["success"],
                "nan_actions": jnp.zeros((), jnp.int32)}

    return rollout


def random_rollout(env, low: float = -1.0, high: float = 1.0) -> Callable:
    """A controller that sends actions uniform in ``[low, high]^A`` every step (same
    interface as :func:`expert_rollout`; ``params`` unused)."""
    import jax
    import jax.numpy as jnp

    n = int(env.config.episode_length)

    def rollout(params, key, mirrored=False):
        k0, k1 = jax.random.split(key)
        s0 = env.reset(k0)
        s0 = jax.lax.cond(mirrored, env.mirror_state, lambda s: s, s0)

        def body(s, k):
            a = jax.random.uniform(k, (env.action_size,), minval=low, maxval=high)
            s = env.step(s, a, observe=False)
            return s, s.info["success"]

        final, succ = jax.lax.scan(body, s0, jax.random.split(k1, n))
        return {"success": final.info["success"], "success_t": succ,
                "nan_actions": jnp.zeros((), jnp.int32)}

    return rollout


# ----------------------------------------------------------------------------- command line

def cli_main(args: list[str], command: str = "") -> dict | None:
    """``equibim experiment NAME [--quick] [--out-dir DIR] [--only CELL ...] [--estimate]
    [--list] [--no-progress]``. ``--estimate`` prints the full size's extrapolated wall
    time from the units measured in ``--out-dir`` (e.g. a quick run's) and runs nothing;
    ``--list`` prints the cells and units and runs nothing."""
    import argparse

    p = argparse.ArgumentParser(prog="equibim experiment", description=(
        "Run (or resume) an experiment of tasks/experiments/NAME.json: cells x arms, each unit "
        "(dataset, training run, evaluation) done once and recorded in OUT/manifest.json."))
    p.add_argument("name", help="experiment name (tasks/experiments/NAME.json) or a JSON file path")
    p.add_argument("--quick", action="store_true", help="the file's quick size (minutes, not days)")
    p.add_argument("--out-dir", default=None,
                   help=f"output folder (default {DEFAULT_OUT}, or {DEFAULT_OUT}-quick with --quick)")
    p.add_argument("--only", nargs="+", default=None, metavar="CELL",
                   help="run only the cells whose name is or starts with one of these")
    p.add_argument("--estimate", action="store_true",
                   help="print the full size's wall-time extrapolation from the measured units; run nothing")
    p.add_argument("--list", action="store_true", help="print the cells; run nothing")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    a = p.parse_args(args)
    exp = load_experiment(a.name, quick=a.quick, only=tuple(a.only) if a.only else None)
    out = Path(a.out_dir if a.out_dir is not None else (DEFAULT_OUT + "-quick" if a.quick else DEFAULT_OUT))
    if a.list:
        for c in exp.cells:
            print(f"{c.name}: task {c.task.name} {c.task.options}, policy {c.preset}, {c.demos} demos, "
                  f"{c.train.total_steps} steps, {c.eval.episodes} episodes/side, evals {[e[0] for e in c.evals]}")
        print(f"{len(exp.cells)} cells x {len(exp.arms)} arms {list(exp.arms)}")
        return None
    if a.estimate:
        full = load_experiment(a.name, quick=False, only=tuple(a.only) if a.only else None)
        est = estimate(full, Manifest(out))
        print(f"{full.name} at full size, extrapolated from the units measured in {out}/manifest.json "
              f"(per-step / per-demo / per-episode-step rates at the size they ran):")
        for k, v in est["by_kind"].items():
            print(f"  {k:<6} {v / 3600:8.2f} h")
        print(f"  total  {est['total_s'] / 3600:8.2f} h")
        if est["missing"]:
            print(f"  no measured rate for {len(est['missing'])} units (not counted): {est['missing'][:5]} ...")
        return est
    res = run_experiment(exp, out, progress=not a.no_progress, command=command)
    print((out / exp.name / "table.md").read_text())
    print(f"wrote {out / exp.name}/results.json, table.md, plot.png")
    return res
