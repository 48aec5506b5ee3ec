"""Reconstruct one stereo frame with the Python API and print a grasp point.

    python examples/reconstruct_frame.py                       # a bundled sample frame
    python examples/reconstruct_frame.py LEFT RIGHT CALIB [--calib-right RIGHT_INFO] [--units mm]

LEFT and RIGHT may be raw (distorted, unrectified) images: the calibration says so, and they
are undistorted and rectified before the reconstruction. The curve comes back in the left
camera's own frame (OpenCV axes: x right, y down, z forward) in the calibration's unit. The
grasp point here is the point halfway along the thread (``point_at(0.5)``); a gripper needs
the curve's tangent there too, so it is printed as well.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # run from a checkout without installing

from threadrecon.app.python_api import reconstruct  # noqa: E402  (``from threadrecon import reconstruct`` once packaged)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("left", nargs="?", help="left image (default: a bundled sample frame)")
    parser.add_argument("right", nargs="?", help="right image")
    parser.add_argument("calib", nargs="?", help="calibration file")
    parser.add_argument("--calib-right", help="right ROS camera_info (when CALIB is the left one)")
    parser.add_argument("--units", choices=("mm", "cm", "m"), help="calibration length unit")
    args = parser.parse_args()

    if args.left is None:
        sample = ROOT / "sample_data" / "simulated" / "flat"
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
        print(f"reconstruction failed: {'; '.join(result.reasons)}", file=sys.stderr)
        return 1
    grasp = result.point_at(0.5)
    tangent = result.point_at(0.51) - result.point_at(0.49)
    tangent /= np.linalg.norm(tangent)
    print(
        f"{len(result.points)} points, length {result.length:.1f} {result.unit}, frame {result.frame}"
    )
    print(f"grasp point ({result.unit}): {np.array2string(grasp, precision=2)}")
    print(f"thread direction there:  {np.array2string(tangent, precision=3)}")
    print(f"total time {sum(result.timings_ms.values()):.0f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
