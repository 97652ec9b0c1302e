"""`equibim symmetry` on any MJCF: the mirror map it writes, and its exit status."""

import json
import warnings

import numpy as np
import pytest

import mjcf_fixtures as fx
from equibim_jax import symmetry as sy
from equibim_jax.cli import main


@pytest.fixture
def mjcf(tmp_path):
    def write(name, xml):
        p = tmp_path / name
        p.write_text(xml)
        return str(p)

    return write


def test_cli_aloha_like_writes_mirror_map(mjcf, tmp_path, capsys):
    path, out = mjcf("aloha.xml", fx.aloha_like_xml()), tmp_path / "maps" / "aloha.json"
    main(["symmetry", "--mjcf", path, "--mirror-normal", "1", "0", "0", "--n-verify", "16", "--out", str(out)])
    printed = capsys.readouterr().out
    assert "left/waist ↔ right/waist" in printed and "lower_forearm_link" in printed
    d = json.loads(out.read_text())
    assert d["format_version"] == 1 and d["mirror"]["normal"] == [1.0, 0.0, 0.0]
    for k in ("qpos", "qvel", "ctrl"):
        assert set(d[k]) >= {"perm", "sign", "offset"}
    assert 0 < d["residual_m"] < 1e-4 and d["dynamics"]["exact"] is False
    assert d["dynamics"]["max_com_offset_m"] == pytest.approx(fx.ALOHA_COM_OFFSET, abs=1e-5)
    assert {c["camera"]: (c["mirror"], c["flip"]) for c in d["cameras"]}["left/wrist_cam"] == (
        "right/wrist_cam", "horizontal")
    assert {p["site"]: p["mirror"] for p in d["ee_action"]["pairs"]} == {"left/ee": "right/ee",
                                                                          "right/ee": "left/ee"}
    # The file is a ModelSymmetry for this model.
    model = fx.load(fx.aloha_like_xml())
    sym = sy.load_mirror_map(out, model)
    ref = sy.derive_symmetry(model, sy.Mirror((1.0, 0.0, 0.0)))
    np.testing.assert_array_equal(sym.qpos.perm, ref.qpos.perm)
    np.testing.assert_array_equal(sym.ctrl.signs, ref.ctrl.signs)


def test_cli_strict_refusal_exits_nonzero_with_report(mjcf, tmp_path, capsys):
    path, out = mjcf("so.xml", fx.so101_pair_xml()), tmp_path / "so.json"
    with pytest.raises(SystemExit) as e:
        main(["symmetry", "--mjcf", path, "--mirror-normal", "0", "1", "0", "--out", str(out)])
    assert e.value.code == 1 and not out.exists()
    err = capsys.readouterr().err
    assert "l_shoulder_lift" in err and "0.036 m" in err and "--approximate" in err
    with pytest.raises(SystemExit) as e:
        main(["symmetry", "--mjcf", mjcf("aloha.xml", fx.aloha_like_xml()), "--mirror-normal", "1", "0", "0",
              "--dynamics", "strict", "--n-verify", "8"])
    assert e.value.code == 1 and "0.014 m" in capsys.readouterr().err


def test_cli_approximate(mjcf, tmp_path, capsys):
    path, out = mjcf("so.xml", fx.so101_pair_xml()), tmp_path / "so.json"
    with warnings.catch_warnings():
        warnings.simplefilter("error", sy.SymmetryWarning)  # reported in the output, not raised
        main(["symmetry", "--mjcf", path, "--mirror-normal", "0", "1", "0", "--approximate", "--n-verify", "16",
              "--out", str(out)])
    printed = capsys.readouterr().out
    assert "body 'l_upper_arm' ↔ 'r_upper_arm': 0.036 m" in printed and "warning: joint 'l_wrist_roll'" in printed
    d = json.loads(out.read_text())
    assert d["approximate"] is True and d["residual_m"] == pytest.approx(2 * fx.SO_LIFT_OFFSET)
    res = {b["body"]: b["residual_m"] for b in d["bodies"]}
    assert res["l_shoulder"] == pytest.approx(0.0, abs=1e-9) and res["r_jaw"] == pytest.approx(0.036)
    ranges = {j["joint"]: j["range"] for j in d["joints"]}
    assert ranges["l_wrist_roll"] == pytest.approx([-2.744, 2.744])
    # A tolerance below the residual: non-zero exit, per-body report.
    with pytest.raises(SystemExit) as e:
        main(["symmetry", "--mjcf", path, "--mirror-normal", "0", "1", "0", "--approximate", "--tol", "0.02",
              "--n-verify", "8"])
    err = capsys.readouterr().err
    assert e.value.code == 1 and "body 'l_upper_arm' residual 0.036 m" in err and "warning:" in err


def test_cli_builtin_robot_and_bad_arguments(mjcf, tmp_path, capsys):
    out = tmp_path / "robot_b.json"
    main(["symmetry", "--robot", "robot_b", "--n-verify", "8", "--out", str(out)])
    d = json.loads(out.read_text())
    assert d["residual_m"] == 0.0 and d["dynamics"]["exact"] is True
    assert len(d["ee_action"]["ee_sites"]) == 2
    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        main(["symmetry", "--mjcf", mjcf("a.xml", fx.aloha_like_xml())])
    assert e.value.code == 2 and "--mirror-normal" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        main(["symmetry", "--mjcf", str(tmp_path / "missing.xml"), "--mirror-normal", "1", "0", "0"])
    assert e.value.code == 2 and "cannot load" in capsys.readouterr().err
