"""The first-person GIF of experiments/report.py: one frame per step, each showing that step's camera image
and predictions."""
import numpy as np
from PIL import Image

from experiments import report


def _frames(path):
    gif = Image.open(path)
    frames = []
    for i in range(gif.n_frames):
        gif.seek(i)
        frames.append(np.asarray(gif.convert("RGB"), dtype=np.int16))
    return frames


def _camera_region(frame):
    """The left quarter of a frame, where the camera image is drawn."""
    return frame[:, : frame.shape[1] // 4]


def test_fpv_gif_has_a_frame_per_step_that_follows_the_camera_and_the_predictions(tmp_path):
    steps, horizon = 5, 6
    images = np.zeros((steps, 36, 64, 3), np.uint8)
    images[2] = 255  # one white camera frame among black ones
    preds = {"collision": np.linspace(0, 1, steps * horizon, dtype=np.float32).reshape(steps, horizon),
             "heading": np.ones((steps, horizon, 2), np.float32)}  # an angle cue, drawn as its angle
    report.write_fpv_gif(tmp_path / "fpv.gif", images, preds, {}, title="caps")  # no truth to draw

    frames = _frames(tmp_path / "fpv.gif")
    assert len(frames) == steps
    assert Image.open(tmp_path / "fpv.gif").info["duration"] == 250  # 4 frames per second by default
    brightness = [_camera_region(f).mean() for f in frames]
    assert brightness[2] > max(brightness[:2] + brightness[3:]) + 20  # the white frame shows at its step only
    assert _plots_change_every_step(frames)  # the predicted curve moves


def test_fpv_gif_draws_the_truth_ahead_of_each_step(tmp_path):
    steps, horizon = 5, 6
    # Predictions that never move, spanning [0, 1] so that the truth lies inside the plot's limits.
    preds = {"collision": np.tile(np.linspace(0, 1, horizon, dtype=np.float32), (steps, 1))}
    signals = {"collision": np.array([0, 1, 0, 1, 0], np.float32)}  # the heading's truth left out
    report.write_fpv_gif(tmp_path / "fpv.gif", np.zeros((steps, 36, 64, 3), np.uint8), preds, signals)
    assert _plots_change_every_step(_frames(tmp_path / "fpv.gif"))  # the true values' dots move


def _plots_change_every_step(frames):
    """Whether the plots right of the camera image differ clearly between each two steps: a moved curve or dot
    changes some hundred pixels, while the GIF's per-frame palette alone shifts a few colours slightly."""
    plots = [f[:, f.shape[1] // 3:] for f in frames]
    return all((np.abs(a - b).sum(-1) > 60).sum() > 50 for a, b in zip(plots[:-1], plots[1:]))


def test_fpv_gif_takes_gray_images(tmp_path):
    images = np.stack([np.full((36, 64, 1), v, np.uint8) for v in (0, 128, 255)])
    report.write_fpv_gif(tmp_path / "fpv.gif", images, {"door_frac": np.zeros((3, 4), np.float32)}, {})
    brightness = [_camera_region(f).mean() for f in _frames(tmp_path / "fpv.gif")]
    assert brightness[0] < brightness[1] < brightness[2]
