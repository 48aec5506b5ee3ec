"""Tests of core/instrument.py: an instrument's jaws are told from the thread by their width."""

from dataclasses import replace

import cv2
import numpy as np
import pytest

from threadrecon.core.instrument import drop_attached, grow_into_attached
from threadrecon.core.segmentation import SegmentationParams, StereoPair, segment
from threadrecon.core.synthetic import RenderParams, SyntheticParams, ThreadParams, generate_frame


def _scene() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A tool block, a 2 px thread under it (one side touching), a 8 px jaw stub on it, and a
    2 px thread piece elsewhere: (mask, tool, jaw, thread)."""
    tool = np.zeros((100, 200), bool)
    tool[40:60, 80:120] = True
    jaw = np.zeros_like(tool)
    jaw[10:40, 96:104] = True  # 8 px wide, attached to the tool's top
    thread = np.zeros_like(tool)
    thread[70:72, 10:190] = True  # free
    thread[50:52, 20:80] = True  # touches the tool's left side
    return jaw | thread, tool, jaw, thread


def test_a_wide_stub_attached_to_the_tool_is_dropped_and_the_thread_kept() -> None:
    mask, tool, jaw, thread = _scene()
    out = drop_attached(mask, tool)
    assert not (out & jaw).any()
    assert np.array_equal(out, thread)


def test_a_stub_as_thin_as_the_thread_is_kept() -> None:
    mask, tool, _, _ = _scene()
    mask[10:40, 96:104] = False
    mask[10:40, 99:101] = True  # a 2 px piece: a thread end leaving the tool
    assert np.array_equal(drop_attached(mask, tool), mask)


def test_a_wide_piece_away_from_the_tool_is_kept() -> None:
    mask, tool, _, _ = _scene()
    mask[10:40, 96:104] = False
    mask[5:30, 20:28] = True  # wide, but not attached to the instrument
    assert np.array_equal(drop_attached(mask, tool), mask)


def test_the_jaw_is_measured_on_the_body_with_its_highlight() -> None:
    mask, tool, jaw, _ = _scene()
    dark_rims = mask & ~np.pad(np.ones((30, 4), bool), ((10, 60), (98, 98)))  # bright centre
    body = mask.copy()
    assert (drop_attached(dark_rims, tool, body) & jaw).sum() == 0


def test_shapes_are_checked() -> None:
    with pytest.raises(ValueError, match=r"\(4, 4\)"):
        drop_attached(np.zeros((4, 4), bool), np.zeros((4, 5), bool))


@pytest.mark.parametrize("seed", [31, 32, 33, 34])
def test_grasper_jaws_over_a_flat_background_are_not_thread(seed: int) -> None:
    render = RenderParams(instrument=True)
    frame = generate_frame(SyntheticParams(thread=ThreadParams(), render=render), seed)
    lifted = segment(StereoPair(frame.left, frame.right), SegmentationParams())
    assert lifted.method == "threshold"
    for P, M in ((lifted.P_L, frame.mask_left), (lifted.P_R, frame.mask_right)):
        near = cv2.dilate(M.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        assert (P & ~near).sum() <= 0.06 * P.sum()  # the jaws were ~30 %
        assert (P & M).sum() >= 0.8 * M.sum()


def test_without_an_instrument_the_flat_threshold_is_unchanged() -> None:
    frame = generate_frame(SyntheticParams(render=replace(RenderParams(), noise_sigma=1.0)), 35)
    pair = StereoPair(frame.left, frame.right)
    auto = segment(pair)
    strict = segment(pair, SegmentationParams(method="threshold"))
    assert np.array_equal(auto.P_L, strict.P_L) and np.array_equal(auto.P_R, strict.P_R)


def test_grey_parts_wider_than_a_thread_attached_to_the_tool_join_it() -> None:
    tool = np.zeros((100, 200), bool)
    tool[40:60, 80:120] = True
    grey = tool.copy()
    grey[10:40, 95:105] = True  # a 10 px jaw on the tool
    grey[50:52, 10:80] = True  # a 2 px grey (white) thread touching it
    grey[5:30, 20:30] = True  # a wide grey patch away from the tool
    grown = grow_into_attached(grey, tool, 7)
    assert grown[14:40, 96:104].all()  # the opening rounds its free end
    assert not grown[50:52, 10:78].any()
    assert not grown[5:30, 20:30].any()
    assert (grown >= tool).all()


def test_grow_into_attached_checks_its_input() -> None:
    with pytest.raises(ValueError, match="min_width_px"):
        grow_into_attached(np.zeros((4, 4), bool), np.zeros((4, 4), bool), 0)
    with pytest.raises(ValueError, match=r"\(4, 5\)"):
        grow_into_attached(np.zeros((4, 4), bool), np.zeros((4, 5), bool), 3)


def test_a_jaw_touching_the_thread_is_dropped_and_the_thread_kept() -> None:
    # One piece: the thread passes along the jaw's free end; the old piece-mean rule kept all.
    mask, tool, jaw, thread = _scene()
    thread[8:10, 10:190] = True  # touches the jaw's end (rows 10-39)
    mask = jaw | thread
    out = drop_attached(mask, tool)
    assert not (out & jaw).any()
    far = thread.copy()
    far[:, 90:110] = False  # within the disc's reach of the jaw
    assert (out & far).sum() == far.sum()


def test_the_corner_between_a_jaw_and_the_shaft_is_dropped() -> None:
    # A jaw leaving the shaft at a slant: the disc does not reach into the corners it makes
    # with the shaft, and no speck of them is left for a curve to bridge to.
    tool = np.zeros((120, 200), bool)
    tool[60:90, 70:130] = True
    body = tool.copy()
    cv2.line(body.view(np.uint8), (100, 60), (70, 15), 1, 9)
    body &= ~tool
    thread = np.zeros_like(tool)
    thread[100:102, 10:190] = True
    mask = body | thread
    out = drop_attached(mask, tool)
    assert np.array_equal(out, thread)
