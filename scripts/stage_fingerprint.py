"""Per-frame fingerprints of the clustering and ordering results and of the final curve, to show
that a speed-up changed nothing (issue #13: "outputs identical").

    # once per code version (PYTHONPATH selects the package), then compare:
    python scripts/stage_fingerprint.py write before.json DATA_DIR[,DATA_DIR...] [--set ...]
    python scripts/stage_fingerprint.py compare before.json after.json

Per frame: status, e_S, length, check verdict, keypoint count, and hashes of the cluster labels
and keypoints, the order, path, edges, dropped keypoints, node of every pixel, links, pixel_t /
pixel_link, the ordering graph (pieces, junctions, decisions with their costs: exact and to 9
significant digits) and the camera-frame curve. Gap ids are names only (their numbering is not
part of the result): each gap is named by its first pixel.

``write --front`` adds, bit for bit, the front stages' results: the lifted pair (I_L, I_R,
P_L, P_R, grey levels, background, scores), stereo (pixels, d_min, d_next, E_min, E_next,
disparity, points) and reliability (R, reliable); ``compare`` then checks those fields too.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from threadrecon.app.bench import with_overrides  # noqa: E402
from threadrecon.app.dataset import discover  # noqa: E402
from threadrecon.app.evaluation import evaluate_frame  # noqa: E402
from threadrecon.app.presets import resolve_preset  # noqa: E402


def _h(a: Any) -> str:
    a = np.ascontiguousarray(np.asarray(a))
    if a.dtype.kind == "f":
        a = np.where(np.isnan(a), -12345.0, a)
    return hashlib.sha1(a.tobytes() + f"{a.dtype}{a.shape}".encode()).hexdigest()[:12]


def _rounded(x: Any) -> Any:
    if isinstance(x, float):
        return float(f"{x:.9g}")
    if isinstance(x, tuple | list):
        return tuple(_rounded(v) for v in x)
    if hasattr(x, "__dataclass_fields__"):
        return tuple(_rounded(getattr(x, k)) for k in x.__dataclass_fields__)
    return x


def _front(rec: Any) -> dict[str, Any]:
    """Hashes of the segment, stereo and reliability results (``write --front``)."""
    d: dict[str, Any] = {}
    if rec is None:
        return d
    if "segment" in rec.runs:
        s = rec["segment"]
        d["segment"] = (
            "".join(
                _h(a) if a is not None else "none"
                for a in (s.I_L, s.I_R, s.P_L, s.P_R, s.grey_L, s.grey_R, s.score_L, s.score_R)
            )
            + f"{s.background}{s.method}"
        )
    if "stereo" in rec.runs:
        st = rec["stereo"]
        d["stereo"] = (
            "".join(
                _h(getattr(st, k))
                for k in ("pixels", "d_min", "d_next", "E_min", "E_next", "disparity", "points")
            )
            + f"{st.d_range}"
        )
    if "reliability" in rec.runs:
        d["reliability"] = _h(rec["reliability"].R) + _h(rec["reliability"].reliable)
    return d


def _fingerprint(row: dict[str, Any], rec: Any) -> dict[str, Any]:
    d: dict[str, Any] = {
        k: (round(float(row[k]), 6) if isinstance(row.get(k), float) else row.get(k))
        for k in ("status", "e_S_mm", "length_mm", "check", "n_keypoints")
    }
    if rec is not None and "ordering" in rec.runs:
        c, o = rec["clustering"], rec["ordering"]
        K = o.n_clusters
        first: dict[int, int] = {}
        for i, g in enumerate(o.pixel_node.tolist()):
            if g >= K:
                first.setdefault(g, i)
        canon = np.array([first[g] + 10**7 if g >= K else g for g in o.pixel_node.tolist()])
        graph = (o.graph.pieces, o.graph.junctions.tolist())
        d.update(
            clusters=_h(c.labels) + _h(c.keypoints) + _h(c.keypoints_px),
            order=_h(o.order) + _h(o.path_px) + _h(o.edges) + _h(o.dropped),
            nodes=_h(canon),
            links=str(tuple(tuple(sorted(first[g] for g in link)) for link in o.links)),
            pixel_t=_h(o.pixel_t) + _h(o.pixel_link),
            graph=hashlib.sha1(repr((*graph, o.graph.decisions)).encode()).hexdigest()[:12],
            graph9=hashlib.sha1(repr((*graph, _rounded(o.graph.decisions))).encode()).hexdigest()[
                :12
            ],
        )
    if rec is not None and "camera" in rec.runs:
        d["curve"] = _h(rec["camera"].points)
    return d


def _write(args: argparse.Namespace) -> None:
    params = with_overrides(resolve_preset(args.config), args.set)
    out = {}
    with threadpool_limits(1):
        for root in args.data.split(","):
            for frame in discover(root):
                row, rec = evaluate_frame(frame, params)
                out[f"{root}:{frame.id}"] = _fingerprint(row, rec)
                if getattr(args, "front", False):
                    out[f"{root}:{frame.id}"].update(_front(rec))
    Path(args.out).write_text(json.dumps(out, indent=1, sort_keys=True))
    print(f"{len(out)} frames -> {args.out}")


def _same(a: Any, b: Any) -> bool:
    nan = isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b)
    return a == b or nan


def _flat(d: Any) -> dict[str, Any]:
    """A frame's fingerprint with nested dicts (e.g. a check's run and re-run) as "a.b" keys."""
    out: dict[str, Any] = {}
    for k, v in (d or {}).items():
        if isinstance(v, dict):
            out.update({f"{k}.{f}": x for f, x in v.items()})
        else:
            out[k] = v
    return out


def compare(args: argparse.Namespace) -> int:
    """``compare BEFORE AFTER [-v]`` of this script and of the other fingerprint scripts
    (scripts/seg_fingerprint.py, scripts/check_identity.py): the fields that differ, per
    field the number of frames; exit 1 if any does."""
    a = json.loads(Path(args.before).read_text())
    b = json.loads(Path(args.after).read_text())
    if set(a) != set(b):
        print(f"different frames: {sorted(set(a) ^ set(b))}")
        return 1
    fields: dict[str, int] = {}
    for k in sorted(a):
        fa, fb = _flat(a[k]), _flat(b[k])
        diff = [f for f in sorted(set(fa) | set(fb)) if not _same(fa.get(f), fb.get(f))]
        for f in diff:
            fields[f] = fields.get(f, 0) + 1
        if diff and args.verbose:
            print(k, {f: (fa.get(f), fb.get(f)) for f in diff})
    print(f"{len(a)} frames; fields that differ (frames): {fields or 'none'}")
    return 0 if not fields else 1


def parser(doc: str) -> tuple[argparse.ArgumentParser, argparse.ArgumentParser]:
    """The fingerprint scripts' command line: ``write OUT DATA[,DATA...] [--config]
    [--set ...]`` and ``compare BEFORE AFTER [-v]``; returns the parser and its ``write``
    sub-parser (for a script's own options)."""
    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    w = sub.add_parser("write")
    w.add_argument("out")
    w.add_argument("data", help="dataset folders, comma-separated")
    w.add_argument("--config", default=None)
    w.add_argument("--set", action="append", default=[], metavar="STAGE.NAME=VALUE")
    c = sub.add_parser("compare")
    c.add_argument("before")
    c.add_argument("after")
    c.add_argument("-v", "--verbose", action="store_true")
    return ap, w


def main() -> int:
    ap, w = parser(__doc__)
    w.add_argument("--front", action="store_true", help="also the front stages' results")
    args = ap.parse_args()
    if args.cmd == "write":
        _write(args)
        return 0
    return compare(args)


if __name__ == "__main__":
    sys.exit(main())
