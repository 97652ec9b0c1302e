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
