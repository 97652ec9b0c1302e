"""`equibim experts`: the expert-success table, its JSON, resuming, and bad input."""

import json

import pytest

from equibim_jax.cli import main
from equibim_jax.evaluation import experts as ex
from equibim_jax.tasks import task_entry, task_names


def _fake(calls):
    def fake(task, episodes, seed, batch, options, progress):
        calls.append(task)
        k = episodes - 1
        return {"success": k / episodes, "ci95": list(ex.wilson_interval(k, episodes)), "episodes": episodes,
                "successes": k, "seed": seed, "options": dict(options)}
    return fake


def test_table_writes_json_and_resumes(tmp_path, monkeypatch, capsys):
    calls = []
    monkeypatch.setattr(ex, "expert_success", _fake(calls))
    out = tmp_path / "r" / "experts.json"
    main(["experts", "--episodes", "10", "--tasks", "stamp_seal", "click_bell", "--out", str(out)])
    d = json.loads(out.read_text())
    assert set(d) == {"stamp_seal", "click_bell"} and d["click_bell"]["episodes"] == 10
    lo, hi = d["click_bell"]["ci95"]
    assert lo < 0.9 < hi <= 1.0
    assert "| `click_bell` | 9/10 (90.0 %)" in capsys.readouterr().out
    # a rerun with the same settings skips both; other settings redo them
    main(["experts", "--episodes", "10", "--tasks", "stamp_seal", "click_bell", "--out", str(out)])
    assert calls == ["stamp_seal", "click_bell"]
    main(["experts", "--episodes", "12", "--tasks", "click_bell", "--out", str(out)])
    assert calls[-1] == "click_bell" and json.loads(out.read_text())["click_bell"]["episodes"] == 12
    assert json.loads(out.read_text())["stamp_seal"]["episodes"] == 10  # kept
    # with no --tasks every task with an expert is run, then the robotwin_faithful variants
    calls.clear()
    main(["experts", "--episodes", "3", "--out", str(tmp_path / "all.json")])
    names = [n for n in task_names() if task_entry(n).expert is not None]
    faithful = [n for n in names if "robotwin_faithful" in task_entry(n).scene_fields]
    assert calls == names + faithful and len(names) >= 8 and len(faithful) == 2
    d = json.loads((tmp_path / "all.json").read_text())
    assert d["handover_block:robotwin_faithful=True"]["options"] == {"robotwin_faithful": "True"}
    assert "| `handover_block`, `robotwin_faithful=True` |" in capsys.readouterr().out


def test_bad_input(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(ex, "expert_success", _fake([]))
    with pytest.raises(SystemExit) as e:
        main(["experts", "--tasks", "no_such_task"])
    assert e.value.code == 2 and "unknown task 'no_such_task'" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["experts", "--episodes", "0", "--tasks", "click_bell"])
    assert "--episodes must be >= 1" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["experts", "--tasks", "click_bell:side"])
    assert "options must be option=value" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["experts", "--tasks", "click_bell:colour=red"])
    assert "unknown option(s) ['colour']" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["experts", "--tasks", "click_bell:side=middle"])
    assert "side must be one of" in capsys.readouterr().err
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(SystemExit):
        main(["experts", "--tasks", "click_bell", "--out", str(bad)])
    assert "is not a JSON file of expert results" in capsys.readouterr().err
    assert bad.read_text() == "{not json"  # nothing on disk is lost
    monkeypatch.undo()
    with pytest.raises(ValueError, match="episodes must be >= 1"):
        ex.expert_success("click_bell", episodes=0)


@pytest.mark.slow
def test_expert_success_runs_the_expert():
    r = ex.expert_success("click_bell", episodes=6, seed=3, batch=4, progress=False)
    assert r["episodes"] == 6 and r["successes"] == 6 and r["failed"] == []
    assert r["length"] == 400 and set(r["side_success"]) == {"left", "right"}
    assert r["compile_s"] > 0 and r["run_s"] > 0
