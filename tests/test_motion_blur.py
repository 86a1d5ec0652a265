"""Motion blur of the insertion (render.shutter, photoreg.render.motion_blur): the geometry of the blur on hand-made
arrays, and the composites against Mitsuba's renders of a camera turning while its shutter is open
(`photoreg synth --camera pan --shutter S`)."""
from __future__ import annotations

import dataclasses
import json

import cv2
import numpy as np
import pytest

from photoreg import cli
from photoreg.config import Session, load_session, validate
from photoreg.device import init_warp
from photoreg.io.images import read_exr, srgb_to_linear
from photoreg.io.recording import iter_frames, open_recording
from photoreg.pipeline import Pipeline
from photoreg.render.composite import Layers, composite, layers_of
from photoreg.render.motion_blur import MAX_GAP_S, Motion, blurred_composite, motion
from photoreg.types import Intrinsics

K = Intrinsics(64, 48, 60.0, 60.0, 31.5, 23.5)
DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(   # the blur kernel's devices (kernels.blur)
    not init_warp().is_cuda_available(), reason="no CUDA device here (runs on the GPU machine: gpu_run.sh blur)"))]


def _moved(dx: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = dx
    return T


def _line_layers() -> Layers:
    """An object of colour 1 covering a vertical line (column 30, rows 10-29) of a 64 x 48 frame."""
    alpha = np.zeros((48, 64), np.float32)
    alpha[10:30, 30] = 1.0
    return Layers(np.repeat(alpha[..., None], 3, axis=-1), alpha, np.ones((48, 64, 3), np.float32),
                  region=(30, 10, 31, 30))


@pytest.mark.parametrize("device", DEVICES)
def test_an_insertion_spreads_along_the_image_motion(device):
    """The camera 10 cm to the left at the previous frame, a wall 2 m ahead: every pixel moved 3 px (fx 0.1 / 2);
    with the shutter open for twice the frame interval the object (a vertical line of 1 on a black frame) spreads
    over 6 px along x and not along y, each row keeping its sum, and the region grows to hold it; a blur under half a
    pixel gives the sharp composite. Without a region (a renderer that names none) the box is where the layers change
    the frame."""
    camera = np.zeros((48, 64, 3), np.float32)
    depth = np.full((48, 64), 2.0, np.float32)
    depth[0, 0] = np.nan                                      # unknown depth is filled, not propagated
    layers = _line_layers()
    blurred, region = blurred_composite(camera, layers, depth, K, Motion(np.eye(4), _moved(-0.1), 2.0), device)
    assert np.isfinite(blurred).all() and blurred.min() >= 0
    rows = blurred[12:28, :, 0]
    np.testing.assert_allclose(rows.sum(axis=1), 1.0, atol=1e-5)
    spread = np.nonzero(rows.max(axis=0) > 1e-6)[0]
    assert spread.min() >= 26 and spread.max() <= 34 and spread.max() - spread.min() >= 5, spread
    assert rows.max() < 0.2                                   # 1 over 6 px
    assert np.all(blurred[:9] == 0) and np.all(blurred[31:] == 0)
    x0, y0, x1, y1 = region
    assert x0 <= 27 and x1 >= 34 and y0 <= 10 and y1 >= 30
    anywhere, box = blurred_composite(camera, dataclasses.replace(layers, region=None), depth, K,
                                      Motion(np.eye(4), _moved(-0.1), 2.0), device)
    np.testing.assert_allclose(anywhere, blurred, atol=1e-6)
    assert box[0] <= 27 and box[2] >= 34
    still, box = blurred_composite(camera, layers, depth, K, Motion(np.eye(4), _moved(-0.1), 0.1), device)
    np.testing.assert_array_equal(still, composite(camera, layers))
    assert box == (30, 10, 31, 30)


@pytest.mark.parametrize("device", DEVICES)
def test_the_frame_does_not_show_through_a_blurred_object(device):
    """An opaque object (colour 0.5) 20 px wide over a striped frame, blurred by 6 px: well inside it the composite is
    the object's colour alone, the stripes behind it nowhere (blurring the composite less the frame let the frame's
    stripes less their blur through), and at its edges the frame shows through by the object's blurred coverage."""
    camera = np.zeros((48, 64, 3), np.float32)
    camera[:, ::2] = 1.0                                       # stripes one pixel wide
    alpha = np.zeros((48, 64), np.float32)
    alpha[10:30, 20:40] = 1.0
    layers = Layers(np.full((48, 64, 3), 0.5, np.float32) * alpha[..., None], alpha, np.ones((48, 64, 3), np.float32),
                    region=(20, 10, 40, 30))
    out, _ = blurred_composite(camera, layers, np.full((48, 64), 2.0, np.float32), K,
                               Motion(np.eye(4), _moved(-0.1), 2.0), device)
    np.testing.assert_allclose(out[12:28, 24:36], 0.5, atol=1e-6)
    edge = out[12:28, 18:22].mean()
    assert 0.3 < edge < 0.7                                    # half object, half the stripes' mean (0.5)
    np.testing.assert_array_equal(out[:, :14], camera[:, :14])


def test_motion_needs_a_shutter_and_a_recent_previous_frame():
    """The shutter's share of the time since the previous frame; none without a shutter time, a previous frame, or
    with one out of order or more than MAX_GAP_S back (its pose does not give the velocity)."""
    pose = np.eye(4)
    m = motion(pose, 1.0, (1.0 - 1 / 30, _moved(-0.1)), 1 / 60)
    assert m is not None and m.share == pytest.approx(0.5)
    assert motion(pose, 1.0, (0.9, pose), 0.0) is None and motion(pose, 1.0, None, 0.01) is None
    assert motion(pose, 1.0, (1.0, pose), 0.01) is None and motion(pose, 1.0, (1.0 - 2 * MAX_GAP_S, pose), 0.01) is None
    s = Session()
    for bad in (-0.01, "fast"):
        s.render.shutter = bad
        with pytest.raises(ValueError, match="render.shutter must be seconds in 0..1 or 'camera'"):
            validate(s)


@pytest.fixture(scope="module")
def pan(tmp_path_factory) -> dict[str, object]:
    """The generated tabletop seen by a camera orbiting it and turning left and right as it goes (16 frames at
    64 x 48), its shutter open for 16 ms (at frame 4 it turns fastest: about 4 px of blur) and, with the same seeds,
    for an instant."""
    root = tmp_path_factory.mktemp("pan")
    out = {}
    for name, shutter in (("blurred", "0.016"), ("sharp", "0")):
        out[name] = root / name
        assert cli.main(["synth", "tabletop", "--out", str(out[name]), "--frames", "16", "--size", "64x48", "--spp",
                         "256", "--camera", "pan", "--insert-frames", "4", "--shutter", shutter, "--no-noise"]) == 0
    return out


def _roi(rec) -> np.ndarray:
    mask = cv2.imread(str(rec / "insert_mask" / "000004.png"))[..., 0] > 0
    return cv2.dilate(mask.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0


def test_the_true_insertion_blurred_matches_mitsuba_s(pan):
    """Mitsuba's insertion at frame 4 of the sharp recording (its insert render as layers over its frame:
    composite.layers_of), composited over the blurred frame and blurred by the camera's motion from frame 3 to 4 at
    the shutter's share (0.016 s x 30 frames/s), comes within half the error of the same insertion left sharp, against
    Mitsuba's blurred insert render; a share twice too long does worse than the right one."""
    meta = json.loads((pan["blurred"] / "scene.json").read_text())
    assert meta["camera"]["shutter_s"] == 0.016 and "--shutter 0.016" in meta["command"]
    assert "at 32 samples per pixel each (256 in all)" in meta["camera"]["shutter"]   # what was rendered, said
    sharp, blurred = open_recording(pan["sharp"]), open_recording(pan["blurred"])
    f1, f2, b2 = sharp.frame(3), sharp.frame(4), blurred.frame(4)
    layers = layers_of(read_exr(pan["sharp"] / "insert" / "000004.exr"), srgb_to_linear(f2.color),
                       cv2.imread(str(pan["sharp"] / "insert_mask" / "000004.png"))[..., 0] > 0)
    cam = srgb_to_linear(b2.color).astype(np.float32)
    truth, roi = read_exr(pan["blurred"] / "insert" / "000004.exr"), _roi(pan["sharp"])

    def error(share: float) -> float:
        if share:
            out, _ = blurred_composite(cam, layers, f2.depth, sharp.intrinsics, Motion(f2.pose, f1.pose, share))
        else:
            out = composite(cam, layers)
        return float(np.sqrt(np.mean((out[roi] - truth[roi]) ** 2)))

    none, right, long = error(0.0), error(0.48), error(0.96)
    assert right < 0.5 * none and right < long, (none, right, long)


def test_the_pipeline_blurs_the_objects_as_the_frame(pan):
    """The blurred recording's session run by the pipeline with render.shutter = 0.016 and without: frame 0 (no
    previous frame) is composited alike; at frame 4, where the camera turns about the vertical, what the objects change
    in the frame is spread sideways (the image motion), as its layers box-blurred 3 px wide would be, not upright,
    and the composites differ only inside the blurred one's region, which holds the sharp one's. With
    render.shutter = "camera" (the default) each frame's own shutter time holds (Frame.shutter: here the recording's
    intrinsics.json, written by the generator; a streamed frame's `shutter`); a number as render.shutter overrides
    it."""
    rec = pan["blurred"]
    results, layers = {}, {}
    keep = "the recording's"   # frames as read: the shutter of the recording's intrinsics.json (0.016)
    for shutter, per_frame in ((0.0, keep), (0.016, keep), ("camera", keep), ("camera", 0.0)):
        s = load_session(rec / "session.toml")
        s.render.shutter, s.device = shutter, "cpu"
        validate(s)
        recording = open_recording(rec)
        pipe = Pipeline(s, recording.intrinsics)
        frames = [f if per_frame is keep else dataclasses.replace(f, shutter=per_frame)
                  for f in iter_frames(recording, range(5))]
        results[shutter, per_frame] = [pipe.process(f) for f in frames]
        layers[shutter, per_frame] = pipe.render.last   # frame 4's
        pipe.close()
    sharp, blurred = results[0.0, keep], results[0.016, keep]
    assert open_recording(rec).shutter == 0.016
    np.testing.assert_array_equal(results["camera", keep][4].composite, blurred[4].composite)
    np.testing.assert_array_equal(results["camera", 0.0][4].composite, sharp[4].composite)
    np.testing.assert_array_equal(sharp[0].composite, blurred[0].composite)
    camera = srgb_to_linear(open_recording(rec).frame(4).color).astype(np.float32)
    alpha, frame_4 = layers[0.0, keep].alpha[..., None], layers[0.0, keep]

    def misfit(kernel: tuple[int, int]) -> float:   # frame 4's layers box-blurred (width, height) against ours
        frame = cv2.blur((1 - alpha) * frame_4.ratio, kernel, borderType=cv2.BORDER_REPLICATE)
        objects = cv2.blur(alpha * frame_4.colour, kernel, borderType=cv2.BORDER_REPLICATE)
        return float(np.abs(camera * frame + objects - blurred[4].composite).sum())

    sideways, upright, none = misfit((3, 1)), misfit((1, 3)), misfit((1, 1))
    assert sideways < 0.3 * none and sideways < 0.3 * upright, (sideways, upright, none)
    x0, y0, x1, y1 = blurred[4].composite_region
    changed = np.abs(blurred[4].composite - sharp[4].composite).max(axis=-1) > 0
    assert changed.any() and not changed[:y0].any() and not changed[y1:].any()
    assert not changed[:, :x0].any() and not changed[:, x1:].any()
    sx0, sy0, sx1, sy1 = sharp[4].composite_region
    assert x0 <= sx0 and y0 <= sy0 and x1 >= sx1 and y1 >= sy1 and (x1 - x0) * (y1 - y0) > (sx1 - sx0) * (sy1 - sy0)
