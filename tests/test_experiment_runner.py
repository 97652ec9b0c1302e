"""The experiment runner (``equibim experiment``): one tiny experiment end to end, resume
(finished units skipped, interrupted units redone), reference controllers through the
evaluation path (the scripted expert succeeds as ``docs/results/experts_200.json`` says,
a random controller does not), bad configs, and (slow) every experiment's quick size."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import jax
import pytest

from equibim_jax.cli import main
from equibim_jax.config import ConfigError
from equibim_jax.evaluation.rollout import evaluate_sides
from equibim_jax.experiments import runner
from equibim_jax.experiments.runner import ARMS, Manifest, load_experiment, run_experiment
from equibim_jax.tasks import make_env

XLA_O0 = True  # compile-bound slow tests: XLA level 0 in `make test-slow` (tests/conftest.py)

REPO = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def smoke(tmp_path_factory):
    """``equibim experiment smoke --quick`` into a fresh folder (the default suite's one
    end-to-end experiment)."""
    out = tmp_path_factory.mktemp("exp")
    main(["experiment", "smoke", "--quick", "--out-dir", str(out), "--no-progress"])
    return out


def _outcomes(x):
    """``x`` without its wall times (which differ between runs)."""
    if isinstance(x, dict):
        return {k: _outcomes(v) for k, v in x.items() if k not in ("wall_s",)}
    return [_outcomes(v) for v in x] if isinstance(x, list) else x


def _units(out: Path) -> dict:
    return json.loads((out / "manifest.json").read_text())["units"]


@pytest.mark.slow  # the smoke experiment compiles generation, training and evaluation (minutes cold)
def test_smoke_outputs(smoke):
    res = json.loads((smoke / "smoke" / "results.json").read_text())
    assert res["quick"] is True and res["arms"] == ["baseline", "equibim"]
    (cell,) = res["cells"].values()
    for arm in ("baseline", "equibim"):
        for side in ("trained", "mirrored"):
            s = cell["evals"]["train_dist"][arm][side]
            assert s["episodes"] == 2 and len(s["per_episode"]) == 2
            assert 0.0 <= s["ci95"][0] <= s["success"] <= s["ci95"][1] <= 1.0
    t = cell["sign_tests"]["train_dist"]["equibim"]["mirrored"]
    assert t["pairs"] == 2 and 0.0 <= t["p_b_better"] <= 1.0
    # the arms differ only in L_sym: the baseline never ran the mirrored branch
    assert cell["train"]["baseline"]["final"]["sym"] == 0.0 < cell["train"]["equibim"]["final"]["sym"]
    assert cell["train"]["baseline"]["steps"] == cell["train"]["equibim"]["steps"] == 4
    md = (smoke / "smoke" / "table.md").read_text()
    assert "| click_bell/dp3_state | train_dist | mirrored |" in md and "Quick size" in md
    assert (smoke / "smoke" / "plot.png").read_bytes()[:4] == b"\x89PNG"
    units = _units(smoke)
    assert sorted(u["kind"] for u in units.values()) == ["data", "eval", "train", "train"]
    assert all(u["wall_s"] > 0 for u in units.values())
    # an estimate for the full size from these measured units covers every unit
    est = runner.estimate(load_experiment("smoke"), Manifest(smoke))
    assert est["missing"] == [] and est["total_s"] > 0


@pytest.mark.slow  # the smoke experiment compiles generation, training and evaluation (minutes cold)
def test_resume_skips_done_and_redoes_interrupted(smoke, monkeypatch):
    from equibim_jax.evaluation import evaluate as ev_mod
    from equibim_jax.training import run as trun

    before = _units(smoke)
    first = json.loads((smoke / "smoke" / "results.json").read_text())["cells"]

    def no_train(*a, **k):
        raise AssertionError("a finished training run was redone")

    def no_eval(*a, **k):
        raise AssertionError("a finished evaluation was redone")

    monkeypatch.setattr(trun, "train_together", no_train)
    monkeypatch.setattr(ev_mod, "evaluate_policies", no_eval)
    main(["experiment", "smoke", "--quick", "--out-dir", str(smoke), "--no-progress"])
    assert _units(smoke) == before  # nothing recorded anew
    again = json.loads((smoke / "smoke" / "results.json").read_text())["cells"]
    assert again == first

    # Interrupted units: a training run whose summary was never written (killed after its
    # checkpoint) and an evaluation with a half-written result file and no manifest record.
    monkeypatch.undo()
    calls = {"train": 0, "eval": 0}
    real_train, real_eval = trun.train_together, ev_mod.evaluate_policies

    def counting_train(*a, **k):
        calls["train"] += 1
        return real_train(*a, **k)

    def counting_eval(*a, **k):
        calls["eval"] += 1
        return real_eval(*a, **k)

    monkeypatch.setattr(trun, "train_together", counting_train)
    monkeypatch.setattr(ev_mod, "evaluate_policies", counting_eval)
    m = Manifest(smoke)
    (tkey, trec), = [(k, u) for k, u in m.units.items() if u["kind"] == "train"][:1]
    (smoke / trec["path"]).unlink()
    (ekey, erec), = [(k, u) for k, u in m.units.items() if u["kind"] == "eval"]
    (smoke / erec["path"]).write_text('{"baseline": {"trained": {"succ')  # torn write
    del m.units[ekey]
    m.record(tkey, **{k: v for k, v in trec.items() if k != "finished"})  # record kept, file gone
    assert ekey not in _units(smoke) and tkey in _units(smoke)
    main(["experiment", "smoke", "--quick", "--out-dir", str(smoke), "--no-progress"])
    assert calls == {"train": 1, "eval": 1}
    after = _units(smoke)
    assert ekey in after and json.loads((smoke / erec["path"]).read_text())["baseline"]["trained"]["episodes"] == 2
    # the redone training resumed from its final checkpoint: no new step
    assert json.loads((smoke / trec["path"]).read_text())["resumed_from"] == 4
    final = json.loads((smoke / "smoke" / "results.json").read_text())["cells"]
    assert _outcomes(final) == _outcomes(first)  # same seed, same keys: the redone units reproduce the results


def test_expert_as_policy_matches_known_success():
    """The scripted expert through the policy-evaluation path (same episode keys, both
    sides) succeeds wherever ``experts_200.json`` (same task, seed 2024) says it does."""
    known = json.loads((REPO / "docs/results/experts_200.json").read_text())["click_bell"]
    env = make_env("click_bell")
    n = 3
    res = evaluate_sides(runner.expert_rollout(env), None, jax.random.key(known["seed"]), n, chunk=n)
    # experts_200.json: every listed start outside "failed" succeeded; it lists none failed
    assert known["failed"] == [] and known["successes"] == known["episodes"]
    assert res["trained"]["per_episode"] == [True] * n
    assert res["mirrored"]["per_episode"] == [True] * n  # the mirror image of a success


@pytest.mark.slow
def test_expert_as_policy_equals_expert_rollout_per_episode():
    from equibim_jax.evaluation.experts import expert_success

    env = make_env("press_stapler")
    n = 4
    res = evaluate_sides(runner.expert_rollout(env), None, jax.random.key(2024), n, chunk=n, sides=("trained",))
    ref = expert_success("press_stapler", episodes=n, seed=2024, batch=n, progress=False)
    assert res["trained"]["successes"] == ref["successes"]
    assert [i for i, s in enumerate(res["trained"]["per_episode"]) if not s] == ref["failed"]


def test_random_policy_fails():
    # (not click_bell: random flailing presses its button now and then)
    env = make_env("place_empty_cup", episode_length=100)
    res = evaluate_sides(runner.random_rollout(env), None, jax.random.key(0), 4, chunk=4)
    assert res["trained"]["successes"] == 0 and res["mirrored"]["successes"] == 0


def _write(tmp_path, **changes) -> str:
    data = json.loads((REPO / "tasks/experiments/smoke.json").read_text())
    for k, v in changes.items():
        if k == "cell":
            data["cells"][0].update(v)
        else:
            data[k] = v
    p = tmp_path / "bad.json"
    p.write_text(json.dumps(data))
    return str(p)


@pytest.mark.parametrize("changes, match", [
    ({"arms": ["baseline", "equibimm"]}, r"unknown arms \['equibimm'\]"),
    ({"arms": ["equibim"]}, "must include 'baseline'"),
    ({"cell": {"task": "no_such_task"}}, "unknown task 'no_such_task'"),
    ({"cell": {"options": {"sidee": "left"}}}, r"unknown options \['sidee'\]"),
    ({"cell": {"policy": "dp9"}}, "unknown policy preset 'dp9'"),
    ({"cell": {"shifts": {"mirror": {"wide_init": 2.0}}}}, r"unknown options \['wide_init'\]"),
    ({"view": "sideways"}, "unknown view"),
    ({"bogus": 1}, r"unknown experiment keys \['bogus'\]"),
    ({"train": {"total_steps": 10, "steps_per_dispatch": 3}}, "TrainConfig"),
    ({"policies": {"dp3_state": {"policy": {"name": "dp3", "widths": 3}}}}, "unknown config fields"),
    ({"policies": {"dp3_state": {"policy": {"name": "nope"}}}}, "nope"),
])
def test_bad_config_clear_error(tmp_path, changes, match):
    with pytest.raises(ConfigError, match=match):
        load_experiment(_write(tmp_path, **changes))


def test_bad_config_from_command_line(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        main(["experiment", _write(tmp_path, arms=["baseline", "nope"]), "--quick"])
    assert e.value.code == 2 and "unknown arms" in capsys.readouterr().err
    with pytest.raises(ConfigError, match="no config file"):
        load_experiment("no_such_experiment")
    with pytest.raises(ConfigError, match="matches no cell"):
        load_experiment("smoke", only=("zzz",))


def test_shipped_experiments_parse():
    """Every shipped experiment parses at both sizes; table2 reuses table1's cells (same
    unit keys) and adds the robotwin_faithful variants; the arms of the ablation exist."""
    t1 = load_experiment("table1")
    assert len(t1.cells) == 32 and {c.preset for c in t1.cells} == {
        "dp_image_joint", "dp_image_ee", "dp3_pc_joint", "dp3_pc_ee"}
    assert all(c.demos == 50 and c.eval.episodes == 100 for c in t1.cells)
    t2 = load_experiment("table2")
    same = [c for c in t2.cells if c.name in {d.name for d in t1.cells}]
    assert len(same) == 32 and all(c == d for c, d in zip(same, t1.cells))
    assert sum(c.task.options.get("robotwin_faithful", False) for c in t2.cells) == 8
    # its own cells resolve against table1's presets and defaults (not a copy that drifts)
    presets = {c.preset: (c.policy, c.train, c.eval, c.demos, c.seed) for c in t1.cells}
    assert all((c.policy, c.train, c.eval, c.demos, c.seed) == presets[c.preset] for c in t2.cells)
    t3 = load_experiment("table3")
    assert {c.task.name: [e[0] for e in c.evals] for c in t3.cells} == {
        "banana_handover": ["train_dist", "mirrored_orientation"], "drumstick_hook": ["train_dist"],
        "chicken_hook": ["train_dist", "wide_init"]}
    ab = load_experiment("ablation")
    assert len(ab.cells) >= 3 and all(c.task.options["side"] == "left" for c in ab.cells)
    cfgs = {a: ab.cells[0].arm_config(a) for a in ab.arms}
    assert cfgs["equibim"].sym_norm == "mse" and cfgs["equibim"].sym_stop_gradient
    assert cfgs["equibim_paper"].sym_norm == "l2" and not cfgs["equibim_paper"].sym_stop_gradient
    assert cfgs["mirror_augment"].mirror_augment and cfgs["mirror_augment"].sym_weight == 0
    assert cfgs["equibim+augment"].mirror_augment and cfgs["equibim+augment"].sym_weight > 0
    assert set(ab.arms) <= set(ARMS)
    for name in ("table1", "table2", "table3", "ablation"):
        q = load_experiment(name, quick=True)
        assert q.quick and all(c.demos <= 2 and c.train.total_steps <= 20 for c in q.cells)


def test_including_experiment_inherits_presets_and_defaults(tmp_path):
    """An including file's cells use the included file's presets, train, eval, demos, seed
    and quick sizes where it gives none; a local preset of the same name, or a local default
    (a quick size too), wins."""
    base = json.loads((REPO / "tasks/experiments/smoke.json").read_text())
    (tmp_path / "base.json").write_text(json.dumps(base))
    preset = next(iter(base["policies"]))
    cell = {"name": "own", "task": base["cells"][0]["task"], "policy": preset}
    inc = {"name": "inc", "include": str(tmp_path / "base.json"), "cells": [cell]}
    (tmp_path / "inc.json").write_text(json.dumps(inc))
    exp = load_experiment(str(tmp_path / "inc.json"))
    own, = (c for c in exp.cells if c.name == "own")
    first = next(c for c in exp.cells if c.name != "own" and c.preset == preset)
    assert (own.policy, own.train, own.eval, own.demos, own.seed) == (
        first.policy, first.train, first.eval, first.demos, first.seed)
    changed = json.loads(json.dumps(base["policies"][preset]))
    changed.setdefault("train", {})["total_steps"] = 2 * own.train.total_steps
    inc.update(policies={preset: changed}, demos=own.demos + 1)
    (tmp_path / "inc.json").write_text(json.dumps(inc))
    own2, = (c for c in load_experiment(str(tmp_path / "inc.json")).cells if c.name == "own")
    assert own2.train.total_steps == 2 * own.train.total_steps and own2.demos == own.demos + 1
    # quick: the included sizes key by key, a local key wins, the included quick.cells never apply
    bq = base.get("quick", {})
    assert bq.get("demos") and bq.get("train")
    base["quick"] = {**bq, "cells": [base["cells"][0].get("name", f"{cell['task']}/{preset}")]}
    (tmp_path / "base.json").write_text(json.dumps(base))
    inc2 = {**inc, "quick": {"demos": bq["demos"] + 1, "cells": ["own"]}}
    (tmp_path / "inc.json").write_text(json.dumps(inc2))
    own_q, = load_experiment(str(tmp_path / "inc.json"), quick=True).cells
    assert own_q.name == "own" and own_q.demos == bq["demos"] + 1
    assert own_q.train.total_steps == bq["train"]["total_steps"]
    with pytest.raises(ConfigError, match="unknown policy preset 'nope'"):
        (tmp_path / "inc.json").write_text(json.dumps({**inc, "cells": [{**cell, "policy": "nope"}]}))
        load_experiment(str(tmp_path / "inc.json"))


def test_merge_previous_keeps_unchanged_cells_only():
    """A table built over several invocations keeps a previous cell only when this run did
    not redo it and its config is unchanged; another experiment, size or arm set keeps none."""
    t1 = load_experiment("table1")
    cfg = {c.name: runner._cell_config(c) for c in t1.cells}
    a, b, c = (x.name for x in t1.cells[:3])
    changed = json.loads(json.dumps(cfg[c]))
    changed["train"]["total_steps"] += 1
    prev = {"experiment": "table1", "quick": False, "arms": list(t1.arms),
            "cells": {a: {"evals": "A"}, b: {"evals": "B"}, c: {"evals": "C"}, "gone/x": {"evals": "G"}},
            "configs": {a: cfg[a], b: cfg[b], c: changed, "gone/x": cfg[a]}}
    kept = runner.merge_previous(prev, "table1", False, list(t1.arms), cfg, ran={b})
    assert list(kept) == [a] and kept[a]["cell"] == {"evals": "A"} and kept[a]["config"] == cfg[a]
    assert runner.merge_previous(prev, "table1", True, list(t1.arms), cfg, ran=set()) == {}
    assert runner.merge_previous(prev, "table2", False, list(t1.arms), cfg, ran=set()) == {}
    assert runner.merge_previous(prev, "table1", False, ["baseline"], cfg, ran=set()) == {}


def test_table_grows_over_invocations(tmp_path, monkeypatch):
    """Two --only invocations into one folder give one table with both cells, each with
    the command that ran it; the units themselves are stubbed (no simulation)."""
    def fake_cell(cell, arms, root, manifest, progress=True, envs=None):
        s = {"success": 0.5, "successes": 1, "episodes": 2, "ci95": [0.1, 0.9], "per_episode": [1, 0]}
        t = {"p_b_better": 0.5, "b_only": 0, "a_only": 0}
        return {"task": cell.task.name, "preset": cell.preset, "options": cell.task.options,
                "evals": {"train_dist": {a: {"trained": s, "mirrored": s} for a in arms}},
                "sign_tests": {"train_dist": {a: {"trained": t, "mirrored": t} for a in arms if a != "baseline"}},
                "train": {}, "units": {}}

    monkeypatch.setattr(runner, "run_cell", fake_cell)
    names = [c.name for c in load_experiment("table1").cells]
    run_experiment(load_experiment("table1", only=(names[1],)), tmp_path, progress=False, command="first")
    res = run_experiment(load_experiment("table1", only=(names[0],)), tmp_path, progress=False, command="second")
    assert list(res["cells"]) == [names[0], names[1]]  # in the experiment file's order
    assert res["cells"][names[1]]["command"] == "first" and res["cells"][names[0]]["command"] == "second"
    assert res["commands"] == ["second", "first"] and set(res["configs"]) == {names[0], names[1]}
    on_disk = json.loads((tmp_path / "table1" / "results.json").read_text())
    assert set(on_disk["cells"]) == {names[0], names[1]}


def test_including_experiment_shows_the_included_tables_cells(tmp_path, monkeypatch):
    """table2 includes table1: a table2 invocation that runs only a robotwin_faithful cell
    shows the table1 cells already in the same folder (same configs) without rerunning
    them, and its own previous cells win over table1's."""
    ran = []

    def fake_cell(cell, arms, root, manifest, progress=True, envs=None):
        ran.append(cell.name)
        s = {"success": 0.5, "successes": 1, "episodes": 2, "ci95": [0.1, 0.9], "per_episode": [1, 0]}
        return {"task": cell.task.name, "preset": cell.preset, "options": cell.task.options,
                "evals": {"train_dist": {a: {"trained": s, "mirrored": s} for a in arms}},
                "sign_tests": {"train_dist": {a: {"trained": t, "mirrored": t} for a in arms if a != "baseline"}},
                "train": {}, "units": {}}

    t = {"p_b_better": 0.5, "b_only": 0, "a_only": 0}
    monkeypatch.setattr(runner, "run_cell", fake_cell)
    t1 = [c.name for c in load_experiment("table1").cells]
    faithful = [c.name for c in load_experiment("table2").cells if c.name not in set(t1)]
    run_experiment(load_experiment("table1", only=(t1[0], t1[1])), tmp_path, progress=False, command="t1")
    res = run_experiment(load_experiment("table2", only=(faithful[0],)), tmp_path, progress=False, command="t2")
    assert ran == [t1[0], t1[1], faithful[0]]
    assert set(res["cells"]) == {t1[0], t1[1], faithful[0]}
    assert res["cells"][t1[0]]["command"] == "t1" and res["cells"][faithful[0]]["command"] == "t2"
    res = run_experiment(load_experiment("table2", only=(t1[0],)), tmp_path, progress=False, command="t2b")
    assert res["cells"][t1[0]]["command"] == "t2b" and res["cells"][t1[1]]["command"] == "t1"
    (tmp_path / "table1" / "results.json").write_text("{not json")
    with pytest.raises(ConfigError, match="table1/results.json is not valid JSON"):
        run_experiment(load_experiment("table2", only=(faithful[0],)), tmp_path, progress=False)
    assert ran[-1] == t1[0]  # the broken file stopped the run before any work


@pytest.mark.parametrize("name", ["table1", "table2", "table3", "ablation"])
def test_committed_cells_match_the_experiment_file(name):
    """The committed results of each experiment were made with the configs its file gives
    now, so a new invocation extends that table instead of dropping its cells."""
    path = REPO / "docs/results/experiments" / name / "results.json"
    if not path.exists():
        pytest.skip(f"no committed results for {name}")
    exp = load_experiment(name)
    prev = json.loads(path.read_text())
    cfg = {c.name: runner._cell_config(c) for c in exp.cells}
    kept = runner.merge_previous(prev, name, False, list(exp.arms), cfg, ran=set())
    assert set(kept) == set(prev["cells"]) and len(kept) >= 1


@pytest.mark.slow
@pytest.mark.parametrize("name", ["table1", "table2", "table3", "ablation"])
def test_quick_experiment_end_to_end(name, tmp_path):
    res = run_experiment(load_experiment(name, quick=True), tmp_path, progress=False)
    for cell in res["cells"].values():
        for label, ev in cell["evals"].items():
            assert set(ev) == set(res["arms"])
    assert (tmp_path / name / "table.md").exists() and (tmp_path / name / "plot.png").exists()
    shutil.rmtree(tmp_path / "units")
