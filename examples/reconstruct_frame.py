"""Reconstruct one stereo frame with the Python API and print a grasp point.

    python examples/reconstruct_frame.py                       # a bundled sample frame
    python examples/reconstruct_frame.py LEFT RIGHT CALIB [--calib-right RIGHT_INFO] [--units mm]

LEFT and RIGHT may be raw (distorted, unrectified) images: the calibration says so, and they
are undistorted and rectified before the reconstruction. The curve comes back in the left
camera's own frame (OpenCV axes: x right, y down, z forward) in the calibration's unit. The
grasp point is the check stage's: the most confident point at the configured distance from
the free end, with the thread's direction there (a gripper needs both) and its confidence.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from threadrecon import reconstruct
from threadrecon.app.resources import sample_data_dir


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("left", nargs="?", help="left image (default: a bundled sample frame)")
    parser.add_argument("right", nargs="?", help="right image")
    parser.add_argument("calib", nargs="?", help="calibration file")
    parser.add_argument("--calib-right", help="right ROS camera_info (when CALIB is the left one)")
    parser.add_argument("--units", choices=("mm", "cm", "m"), help="calibration length unit")
    args = parser.parse_args()

    if args.left is None:
        sample = sample_data_dir() / "simulated" / "flat"
        result = reconstruct(
            None,
            stereo=sample / "flat_1.png",
            mask=sample / "flat_1_mask.png",
            calib=sample / "calibration.yaml",
        )
    else:
        if args.right is None or args.calib is None:
            parser.error("give LEFT, RIGHT and CALIB")
        result = reconstruct(
            args.left, args.right, args.calib, calib_right=args.calib_right, units=args.units
        )

    if not result.ok:
        print(f"reconstruction {result.status}: {'; '.join(result.reasons)}", file=sys.stderr)
        return 1
    g = result.grasp
    print(
        f"{len(result.points)} points, length {result.length:.1f} {result.unit}, frame {result.frame}"
        f", score {result.score}/5"
    )
    print(f"grasp point ({result.unit}): {np.array2string(g.point, precision=2)}")
    print(f"thread direction there:  {np.array2string(g.tangent, precision=3)}")
    print(f"confidence {g.confidence:.2f}, {g.distance:.1f} {result.unit} from the {g.from_end}")
    print(f"total time {sum(result.timings_ms.values()):.0f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
