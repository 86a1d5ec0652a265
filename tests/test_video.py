"""composite.mp4 (photoreg.io.video): frame rate from timestamps, the writer's round trip and its errors, and the
session option that needs objects."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from photoreg.config import Session, validate
from photoreg.io.video import FALLBACK_FPS, VideoOut, frame_rate


def test_frame_rate_from_timestamps():
    assert frame_rate(np.arange(10) / 30.0) == pytest.approx(30.0)
    assert frame_rate(np.array([0.0, 0.1, 0.2, 5.0])) == pytest.approx(10.0)   # a gap does not move the median
    assert frame_rate(np.array([1.0])) == FALLBACK_FPS and frame_rate(np.array([2.0, 2.0])) == FALLBACK_FPS


def test_video_round_trip_and_errors(tmp_path):
    """Frames come back in order at the size and rate given; the video appears under its name only when closed;
    a frame of another size is an error naming the file."""
    path = tmp_path / "composite.mp4"
    v = VideoOut(path, 64, 48, 12.5)
    levels = [0.05, 0.3, 0.8]
    for x in levels:
        v.write(np.full((48, 64, 3), x, np.float32))
    with pytest.raises(ValueError, match="composite.mp4"):
        v.write(np.zeros((10, 10, 3), np.float32))
    assert not path.exists() and v.tmp.exists()
    v.close()
    assert path.is_file() and not v.tmp.exists() and v.frames == 3
    cap = cv2.VideoCapture(str(path))
    assert cap.get(cv2.CAP_PROP_FPS) == pytest.approx(12.5)
    got = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        assert frame.shape == (48, 64, 3)
        got.append(float(frame.mean()))
    assert len(got) == 3 and got[0] < got[1] < got[2]


def test_video_needs_objects():
    s = Session()
    s.output.video = True
    with pytest.raises(ValueError, match="output.video needs"):
        validate(s)
