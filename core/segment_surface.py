"""Does a line move with the tissue around it? A stereo cue of the raw segmentation.

Vessels and fibres are marks on the tissue surface: in the other view they appear at the
disparity of the tissue texture right next to them. A thread is a body of its own: where it
runs in front of the tissue its disparity differs from that of the texture beside it. For a
piece of the left view (the right view: mirrored) the grey residual

    R(d) = mean |A(r, c) - B(r, c - d)|,  0 <= d <= D,

is computed per block of the image (disparity varies along a slanted thread and over a
curved surface) on the piece's own pixels there (its disparity ``d_piece``, the smallest R)
and on the block's background: its pixels away from every candidate line, on a grid, for d
within _WINDOW_PX of ``d_piece``. The background votes only where it resolves its own
disparity (it matches significantly worse _RESOLVE_PX away on both sides: a flat or shaded
background abstains); the piece moves with it where the background's residual at
``d_piece`` (within SAME_DISPARITY_PX) exceeds its least by under half of its rise
_RESOLVE_PX away, i.e. the two disparities are within ~2 px. Tissue texture is smooth: the
background's minimum is broad, and only many pixels tell a few px of disparity apart.

Limit: a thread resting on the tissue along all its visible length moves with it too and is
taken for a mark on it; the raw segmentation asks only about pieces that are otherwise
thread-like (long, thin, with a stereo partner, standing out of the noise).
"""

from __future__ import annotations

from typing import Final

import numpy as np

from threadrecon.core.ridge_kernel import background_vote, block_residuals, excess_stats

SAME_DISPARITY_PX: Final = 1.5  # two disparities within 1.5 px: one surface (the sampling
# of a 1-6 px line blurs its optimum by ~1 px)
_TEXTURED: Final = 0.6  # the piece's least residual below 60 % of its median over d: its
# disparity is defined (noise alone matches at every d alike)
_T_SAME: Final = 3.0  # a background matches worse _RESOLVE_PX off its optimum by >= 3
# standard errors of the mean excess: it resolves its disparity
_RESOLVE_PX: Final = 3  # 2 SAME_DISPARITY_PX
_TAIL: Final = 4.0  # per-pixel excess residuals beyond 4x the block's noise level: a partner
# meeting a line, clipped
_MAX_SAMPLES: Final = 256  # piece pixels sampled per test (evenly): the residual is a mean
_BLOCK_PX: Final = 64  # disparity is compared per 64 px square: a slanted thread's varies by
# ~2 px over it (a 10 px change over a 300 px thread); the tissue's, less
_GRID_PX: Final = 2  # background pixels on a 2 px quincunx grid: 512 per free block (smooth
# tissue needs many to resolve 3 px)
_WINDOW_PX: Final = 8  # the background's residual within 8 px of the piece's disparity: its
# optimum elsewhere (at the window's edge) is "does not move with the piece"
_MAX_VOTES: Final = 4  # blocks that vote per piece: enough for a majority, and a bound on the
# work
_MIN_VOTES: Final = 2  # a piece is judged on two blocks at least (a frame tests tens of
# blocks at 3 sigma: one passes by chance now and then)
_MIN_BLOCK_SAMPLES: Final = 8  # samples a block needs for a disparity of its own
BLOCK_PX: Final = _BLOCK_PX  # (the block's size, for the callers of :func:`block_of`)


def undecidable(rows: np.ndarray, cols: np.ndarray, width: int) -> bool:
    """Whether a piece of pixels (``rows``, ``cols``) in an image ``width`` px wide lies in
    fewer blocks than :class:`SurfaceTest` needs to judge it (it can never be decided)."""
    nb = _blocks_across(width)
    return len(np.unique(_block_keys(rows, cols, nb))) < _MIN_VOTES


def block_of(rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Block row and block column (M,) of the pixels (``rows``, ``cols``) on the grid of
    _BLOCK_PX squares that :meth:`SurfaceTest.votes` votes on (one vote a block)."""
    return rows // _BLOCK_PX, cols // _BLOCK_PX


def _blocks_across(width: int) -> int:
    return (width + _BLOCK_PX - 1) // _BLOCK_PX


def _block_keys(rows: np.ndarray, cols: np.ndarray, nb: int) -> np.ndarray:
    """Each pixel's block, numbered row by row over ``nb`` blocks across."""
    return rows // _BLOCK_PX * nb + cols // _BLOCK_PX


class SurfaceTest:
    """Asks whether pieces of the grey view ``this`` (H, W) float32 move with the tissue
    between ``this`` and the grey other view ``other`` (H, W) float32 (module docstring).
    ``free`` (H, W) bool marks background pixels (away from every candidate line);
    ``look_left``: the partner of (r, c) is at (r, c - d) (this is the left view), else at
    (r, c + d); 0 <= d <= ``max_disparity``."""

    def __init__(
        self,
        this: np.ndarray,
        other: np.ndarray,
        free: np.ndarray,
        max_disparity: int,
        look_left: bool,
    ) -> None:
        if this.shape != other.shape or this.ndim != 2 or free.shape != this.shape:
            raise ValueError(
                f"SurfaceTest needs three (H, W) images of one size, got {this.shape}, "
                f"{other.shape}, {free.shape}"
            )
        # (the residual kernel reads C-ordered float32 images)
        self.this = np.ascontiguousarray(this, np.float32)
        self.other = np.ascontiguousarray(other, np.float32)
        self.free = free
        self.dmax, self.look_left = int(max_disparity), look_left
        self.nb = _blocks_across(this.shape[1])
        self._grid: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def on_surface(self, rows: np.ndarray, cols: np.ndarray) -> bool:
        """Whether the piece of pixels (``rows``, ``cols``) (M,) moves with the background
        on most of its pixels where that is decided (:meth:`votes`)."""
        v = self.votes(rows, cols)
        return bool(np.count_nonzero(v == 1) > 0.5 * np.count_nonzero(v >= 0))

    def votes(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """(M,) int8 per pixel (``rows``, ``cols``) of a piece: 1 where, in its block, the
        piece moves with the background, 0 where it does not, -1 where that is not decided
        (too few pixels, a background without texture, or a block not looked at)."""
        out = np.full(len(rows), -1, np.int8)
        if len(rows) == 0 or self.dmax < 1:
            return out
        key_all = _block_keys(rows, cols, self.nb)
        step = max(len(rows) // _MAX_SAMPLES, 1)
        r, c, key = rows[::step], cols[::step], key_all[::step]
        ids, block = _unique(key, self.nb * ((self.this.shape[0] + _BLOCK_PX - 1) // _BLOCK_PX))
        piece = _Residuals(
            self.this, self.other, r, c, block, len(ids), np.arange(self.dmax + 1), self.look_left
        )
        vote = np.full(len(ids), -1, np.int8)
        cand = np.flatnonzero(piece.defined())
        # Blocks spread over the piece (in the order of their keys, row-major), at most
        # _MAX_VOTES decided ones out of 2 _MAX_VOTES looked at: the work is bounded.
        if len(cand) > 2 * _MAX_VOTES:
            cand = cand[np.linspace(0, len(cand) - 1, 2 * _MAX_VOTES).round().astype(int)]
        for b in cand.tolist():
            d = int(piece.best_d[b])
            rr, cc = self._background(int(ids[b]))
            if len(rr) < _MIN_BLOCK_SAMPLES:
                continue
            # The background's residuals within _WINDOW_PX of d: does it resolve its own
            # disparity, and does it match at d (:meth:`_Residuals.resolves` of the block, then
            # its excess residual at d against the sides', in one compiled call)?
            bv = background_vote(
                self.this, self.other, rr, cc, d, self.dmax, _WINDOW_PX, self.look_left,
                _RESOLVE_PX, _MIN_BLOCK_SAMPLES, SAME_DISPARITY_PX, _TAIL, _T_SAME,
            )  # fmt: skip
            if bv >= 0:
                vote[b] = bv
                if np.count_nonzero(vote >= 0) >= _MAX_VOTES:
                    break
        if np.count_nonzero(vote >= 0) < _MIN_VOTES:
            return out  # one block's vote is no evidence: its t-tests pass by chance at times
        at = np.searchsorted(ids, key_all)
        found = (at < len(ids)) & (ids[np.minimum(at, len(ids) - 1)] == key_all)
        out[found] = vote[at[found]]
        return out

    def disparity(self, rows: np.ndarray, cols: np.ndarray) -> int | None:
        """The best disparity (px) of the pixels (``rows``, ``cols``) (M,) taken together (the
        least mean grey residual over 0..D, on at most _MAX_SAMPLES of them spread evenly),
        or None where it is not defined (too few pixels, or no distinct minimum: a line along
        the rows, a flat patch)."""
        if len(rows) == 0 or self.dmax < 1:
            return None
        step = max(len(rows) // _MAX_SAMPLES, 1)
        r, c = rows[::step], cols[::step]
        res = _Residuals(
            self.this,
            self.other,
            r,
            c,
            np.zeros(len(r), np.intp),
            1,
            np.arange(self.dmax + 1),
            self.look_left,
        )
        return int(res.best_d[0]) if res.defined()[0] else None

    def background_disparity(
        self, rows: np.ndarray, cols: np.ndarray, near: int | None = None
    ) -> int | None:
        """The disparity (px) of the background (the tissue) in the block that holds most of
        the pixels (``rows``, ``cols``) (M,), over 0..D, or None where it does not resolve it
        (:meth:`_Residuals.resolves`: a flat or shaded background, too few samples). Given
        ``near``: the best disparity within _WINDOW_PX of it (the tissue a piece of disparity
        ``near`` there is compared with, :meth:`votes`)."""
        if len(rows) == 0 or self.dmax < 1:
            return None
        keys = _block_keys(rows, cols, self.nb)
        rr, cc = self._background(int(np.bincount(keys).argmax()))
        if len(rr) < _MIN_BLOCK_SAMPLES:
            return None
        if near is None:
            ds = np.arange(self.dmax + 1)
        else:
            ds = np.arange(max(near - _WINDOW_PX, 0), min(near + _WINDOW_PX, self.dmax) + 1)
        bg = _Residuals(
            self.this, self.other, rr, cc, np.zeros(len(rr), np.intp), 1, ds, self.look_left
        )
        return int(bg.best_d[0]) if bg.resolves(0) else None

    def _background(self, key: int) -> tuple[np.ndarray, np.ndarray]:
        """Rows and columns of the background pixels on the grid of block ``key``."""
        if key not in self._grid:
            r0, c0 = key // self.nb * _BLOCK_PX, key % self.nb * _BLOCK_PX
            h, w = self.this.shape
            rr, cc = _GRID_R + r0, _GRID_C + c0
            ok = (rr < h) & (cc < w)  # the last blocks may be cut by the image's edge
            rr, cc = rr[ok], cc[ok]
            ok = self.free[rr, cc]
            self._grid[key] = (rr[ok], cc[ok])
        return self._grid[key]


class _Residuals:
    """Per-pixel grey residuals |A(r, c) - B(r, c -+ d)| (N, len(ds)) of pixels (r, c) (N,)
    at the disparities ``ds`` (consecutive), ``inside`` where the partner is in the image, and their
    mean per block (n_blocks, len(ds)), inf where fewer than half of a block's pixels count."""

    def __init__(
        self,
        this: np.ndarray,
        other: np.ndarray,
        r: np.ndarray,
        c: np.ndarray,
        block: np.ndarray,
        n_blocks: int,
        ds: np.ndarray,
        look_left: bool,
    ) -> None:
        self.ds = ds
        self.diff, self.inside, self.size, self.mean = block_residuals(
            this,
            other,
            np.ascontiguousarray(r, np.int64),
            np.ascontiguousarray(c, np.int64),
            np.ascontiguousarray(block, np.int64),
            n_blocks,
            int(ds[0]) if len(ds) else 0,
            len(ds),
            look_left,
        )  # the pixels grouped by block; means as np.add.reduceat gives them
        self.starts = np.cumsum(self.size) - self.size
        self.best = np.argmin(self.mean, axis=1)
        self.best_d = ds[self.best]
        self.least = self.mean[np.arange(n_blocks), self.best]

    def defined(self) -> np.ndarray:
        """(n_blocks,) bool: enough pixels and a least residual below _TEXTURED times the
        median over d (robust to the few d where the partner meets a line): a disparity of
        its own."""
        srt = np.sort(self.mean, axis=1)  # inf (too few pixels count) last
        n_valid = np.isfinite(srt).sum(axis=1)
        mid = np.maximum(n_valid - 1, 0) // 2
        typical = np.where(n_valid > 0, srt[np.arange(len(srt)), mid], np.inf)
        return (
            (self.size >= _MIN_BLOCK_SAMPLES)
            & np.isfinite(self.least)
            & (self.least < _TEXTURED * typical)
        )

    def resolves(self, b: int) -> bool:
        """Whether block ``b`` tells its best disparity from one _RESOLVE_PX away on either
        side (a flat or shaded background, or a blurred texture, matches nearly as well
        there): both sides (those within ``ds``) match significantly worse."""
        if self.size[b] < _MIN_BLOCK_SAMPLES or not np.isfinite(self.least[b]):
            return False
        sides = self._sides(b)
        return bool(sides) and all(self._worse(b, i) for i in sides)

    def _sides(self, b: int) -> list[int]:
        """Indices into ``ds`` of the disparities _RESOLVE_PX either side of block ``b``'s
        best, where inside ``ds`` (at the window's edge the optimum may lie beyond it)."""
        own = int(self.best[b])
        return [i for i in (own - _RESOLVE_PX, own + _RESOLVE_PX) if 0 <= i < len(self.ds)]

    def _worse(self, b: int, at: int) -> bool:
        """Whether block ``b`` matches significantly worse at index ``at`` of ``ds`` than at
        its best: the mean per-pixel excess residual is >= _T_SAME standard errors."""
        own = int(self.best[b])
        # The pixels whose partner meets a line (a heavy tail) clipped to _TAIL times the
        # block's least mean residual (its noise and texture level); np.mean and np.std of
        # those (float32) by the kernel, to the last bit.
        cap = _TAIL * float(self.least[b]) + 1.0
        n, mean, std = excess_stats(
            self.diff, self.inside, int(self.starts[b]), int(self.size[b]), at, own, np.float32(cap)
        )
        if n < _MIN_BLOCK_SAMPLES:
            return False
        se = std / np.sqrt(n) + 1e-6
        return mean >= _T_SAME * se


def _quincunx() -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns (n,) within a block of the background samples: every _GRID_PX-th
    pixel from _GRID_PX // 2 on, where (row // _GRID_PX + col // _GRID_PX) is even, row-major
    (the order of np.mgrid over a block)."""
    rr, cc = np.mgrid[_GRID_PX // 2 : _BLOCK_PX : _GRID_PX, _GRID_PX // 2 : _BLOCK_PX : _GRID_PX]
    rr, cc = rr.ravel(), cc.ravel()
    ok = (rr // _GRID_PX + cc // _GRID_PX) % 2 == 0
    return rr[ok], cc[ok]


_GRID_R, _GRID_C = _quincunx()  # a block's sample offsets, computed once


def _unique(key: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(key, return_inverse=True)`` of keys (M,) in 0 .. n - 1 (a counting sort)."""
    present = np.bincount(key, minlength=n) > 0
    ids = np.flatnonzero(present)
    rank = np.cumsum(present) - 1
    return ids, rank[key]
