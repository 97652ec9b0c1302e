"""Task pictures: the GIF and the grid from frames, and (slow) frames of a real expert episode."""

import numpy as np
import pytest
from PIL import Image

from equibim_jax.evaluation import pictures as pics


def _frames(t=40, size=32, seed=0):
    rng = np.random.default_rng(seed)
    f = rng.integers(0, 255, (t, size, size, 3), dtype=np.uint8)
    return {"frames": f, "mirror_frames": f[:, :, ::-1], "success": True, "mirror_success": False}


def test_gif_and_grid(tmp_path):
    f = _frames()
    gif = pics.task_gif(f, tmp_path / "g" / "a.gif", every=5)
    im = Image.open(gif)
    assert im.size == (2 * 32 + 4, 32) and im.n_frames == 9  # frames 0, 5, ..., 35 and the last
    # the size cap drops frames until the GIF fits
    capped = pics.task_gif(_frames(t=60, size=48), tmp_path / "b.gif", every=1, max_bytes=60_000)
    assert capped.stat().st_size <= 60_000 and Image.open(capped).n_frames < 60
    png = pics.task_grid({"a": f, "b": _frames(seed=1)}, tmp_path / "grid.png")
    w, h = Image.open(png).size
    assert h > w / 4 * 1.5  # two rows of four panels


@pytest.mark.slow
def test_expert_frames_show_the_mirror_image():
    f = pics.expert_frames("click_bell", seed=0, image_size=32)
    assert f["frames"].dtype == np.uint8 and f["frames"].shape[1:] == (32, 32, 3)
    assert f["success"] and f["mirror_success"]
    assert f["frames"].std() > 10  # not blank
    # the head camera is on the mirror plane: the mirrored start is the flipped start image
    np.testing.assert_array_equal(f["mirror_frames"][0], f["frames"][0][:, ::-1])
    assert np.abs(f["frames"][-1].astype(int) - f["frames"][0]).mean() > 0.5  # the scene moved


def test_make_pictures_reuses_cached_frames_and_names_the_grid(tmp_path):
    """Frames in the cache are used as they are (no simulation); the grid gets its name."""
    cache = tmp_path / "cache"
    cache.mkdir()
    for i, task in enumerate(("banana_handover", "chicken_hook")):
        np.savez_compressed(cache / f"{task}_0_32.npz", **_frames(seed=i))
    out = tmp_path / "docs"
    summary = pics.make_pictures(["banana_handover", "chicken_hook"], out, seed=0, image_size=32,
                                 cache_dir=cache, progress=False, grid="tasks_robot_b.png")
    assert set(summary) == {"banana_handover", "chicken_hook"}
    assert summary["banana_handover"]["success"] is True and summary["chicken_hook"]["mirror_success"] is False
    assert (out / "tasks_robot_b.png").exists() and not (out / "tasks.png").exists()
    assert all((out / "gifs" / f"{t}.gif").stat().st_size > 0 for t in summary)


@pytest.mark.parametrize("grid", ["tasks.jpg", "sub/tasks.png", ".png"])
def test_pictures_cli_refuses_a_bad_grid_name(grid, capsys):
    from equibim_jax.cli import main

    with pytest.raises(SystemExit):
        main(["pictures", "--grid", grid, "--tasks", "click_bell"])
    assert "--grid must be a file name ending in .png" in capsys.readouterr().err
