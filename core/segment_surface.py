"""Does a line move with the tissue around it? A stereo cue of the raw segmentation.

Vessels and fibres are marks on the tissue surface: in the other view they appear at the
disparity of the tissue texture right next to them. A thread is a body of its own: where it
runs in front of the tissue its disparity differs from that of the texture beside it. For a
piece of the left view (the right view: mirrored) the grey residual

    R(d) = mean |A(r, c) - B(r, c - d)|,  0 <= d <= D,

is computed per block of the image (disparity varies along a slanted thread and over a
curved surface) on the piece's own pixels there (its disparity ``d_piece``, the smallest R)
and on the block's background: its pixels away from every candidate line, on a grid (the
tissue's disparity ``d_bg``). The piece lies on the surface where the background is textured
(its smallest R well below its median R) and matches as well at ``d_piece`` (within
SAME_DISPARITY_PX) as at ``d_bg``: the mean per-pixel excess residual there is under _T_SAME
standard errors (tails clipped) (tissue texture is smooth: the background's minimum is broad, and only many
pixels tell a few px of disparity apart).

Limit: a thread resting on the tissue along all its visible length moves with it too and is
taken for a mark on it; the raw segmentation asks only about pieces that are otherwise
thread-like (long, thin, with a stereo partner, standing out of the noise).
"""

from __future__ import annotations

from typing import Final

import numpy as np

SAME_DISPARITY_PX: Final = 1.5  # two disparities within 1.5 px: one surface (the sampling
# of a 1-6 px line blurs its optimum by ~1 px)
_TEXTURED: Final = 0.6  # a residual curve's least value below 60 % of its median over d: its
# disparity is defined (noise alone, or a flat background, matches at every d alike)
_T_SAME: Final = 3.0  # the background matches worse at the piece's disparity by >= 3
# standard errors of the mean excess: it does not move with the piece
_MAX_SAMPLES: Final = 256  # piece pixels sampled per test (evenly): the residual is a mean
_BLOCK_PX: Final = 64  # disparity is compared per 64 px square: a slanted thread's varies by
# ~2 px over it (a 10 px change over a 300 px thread); the tissue's, less
_GRID_PX: Final = 4  # background pixels on a 4 px grid: 256 per free block
_MIN_BLOCK_SAMPLES: Final = 8  # samples a block needs for a disparity of its own


class SurfaceTest:
    """Asks whether pieces of the grey view ``this`` (H, W) float32 move with the tissue
    between ``this`` and the grey other view ``other`` (H, W) float32 (module docstring).
    ``free`` (H, W) bool marks background pixels (away from every candidate line);
    ``look_left``: the partner of (r, c) is at (r, c - d) (this is the left view), else at
    (r, c + d); 0 <= d <= ``max_disparity``. The background's residuals are computed once per
    block, when a piece first needs them."""

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
        self.this, self.other, self.free = this, other, free
        self.dmax, self.look_left = int(max_disparity), look_left
        self.nb = (this.shape[1] + _BLOCK_PX - 1) // _BLOCK_PX
        self._bg: dict[int, _Residuals] = {}

    def on_surface(self, rows: np.ndarray, cols: np.ndarray) -> bool:
        """Whether the piece of pixels (``rows``, ``cols``) (M,) moves with the background
        on most of its pixels where that is decided (:meth:`votes`)."""
        v = self.votes(rows, cols)
        return bool(np.count_nonzero(v == 1) > 0.5 * np.count_nonzero(v >= 0))

    def votes(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """(M,) int8 per pixel (``rows``, ``cols``) of a piece: 1 where, in its block, the
        piece moves with the background, 0 where it does not, -1 where a disparity is missing
        (too few pixels, or no texture to tell)."""
        out = np.full(len(rows), -1, np.int8)
        if len(rows) == 0 or self.dmax < 1:
            return out
        key_all = rows // _BLOCK_PX * self.nb + cols // _BLOCK_PX
        step = max(len(rows) // _MAX_SAMPLES, 1)
        r, c, key = rows[::step], cols[::step], key_all[::step]
        ids, block = np.unique(key, return_inverse=True)
        piece = _Residuals(self.this, self.other, r, c, block, len(ids), self.dmax, self.look_left)
        vote = np.full(len(ids), -1, np.int8)
        for b in np.flatnonzero(piece.defined()).tolist():
            bg = self._background(int(ids[b]))
            if bg.defined()[0] and bg.resolves(0):
                vote[b] = bg.matches_at(0, int(piece.best[b]))
        at = np.searchsorted(ids, key_all)
        found = (at < len(ids)) & (ids[np.minimum(at, len(ids) - 1)] == key_all)
        out[found] = vote[at[found]]
        return out

    def _background(self, key: int) -> _Residuals:
        """The residuals of the background grid pixels of block ``key`` (one block)."""
        if key not in self._bg:
            r0, c0 = key // self.nb * _BLOCK_PX, key % self.nb * _BLOCK_PX
            h, w = self.this.shape
            rr, cc = np.mgrid[
                r0 + _GRID_PX // 2 : min(r0 + _BLOCK_PX, h) : _GRID_PX,
                c0 + _GRID_PX // 2 : min(c0 + _BLOCK_PX, w) : _GRID_PX,
            ]
            rr, cc = rr.ravel(), cc.ravel()
            ok = self.free[rr, cc]
            rr, cc = rr[ok], cc[ok]
            self._bg[key] = _Residuals(
                self.this, self.other, rr, cc, np.zeros(len(rr), np.intp), 1, self.dmax,
                self.look_left,
            )  # fmt: skip
        return self._bg[key]


class _Residuals:
    """Per-pixel grey residuals |A(r, c) - B(r, c -+ d)| (N, dmax + 1) of pixels (r, c) (N,),
    NaN where the partner leaves the image, and their mean per block (n_blocks, dmax + 1)."""

    def __init__(
        self,
        this: np.ndarray,
        other: np.ndarray,
        r: np.ndarray,
        c: np.ndarray,
        block: np.ndarray,
        n_blocks: int,
        dmax: int,
        look_left: bool,
    ) -> None:
        d = np.arange(dmax + 1)
        if len(r) == 0:  # no pixel: nothing is defined
            r = c = block = np.zeros(0, np.intp)
        order = np.argsort(block, kind="stable")
        r, c, self.block = r[order], c[order], block[order]
        cc = c[:, None] - d[None, :] if look_left else c[:, None] + d[None, :]
        inside = (cc >= 0) & (cc < this.shape[1])
        diff = np.abs(this[r, c][:, None] - other[r[:, None], np.clip(cc, 0, this.shape[1] - 1)])
        self.diff = np.where(inside, diff, np.float32(np.nan))
        starts = np.flatnonzero(np.r_[True, self.block[1:] != self.block[:-1]])
        starts = starts[starts < len(self.block)]
        self.starts = np.full(n_blocks, -1)
        self.starts[self.block[starts]] = starts
        self.size = np.bincount(self.block, minlength=n_blocks)
        total = np.zeros((n_blocks, dmax + 1), np.float32)
        count = np.zeros((n_blocks, dmax + 1), np.float32)
        if len(self.block):
            starts = starts[starts < len(self.block)]
            total[self.block[starts]] = np.add.reduceat(diff * inside, starts, axis=0)
            count[self.block[starts]] = np.add.reduceat(inside.astype(np.float32), starts, axis=0)
        valid = count >= np.maximum(0.5 * self.size, 1.0)[:, None]
        self.mean = np.where(valid, total / np.maximum(count, 1.0), np.inf)
        self.best = np.argmin(self.mean, axis=1)
        self.least = self.mean[np.arange(n_blocks), self.best]
        # The median over d: robust to the few d where the partner meets a line
        typical = np.where(np.isfinite(self.mean), self.mean, np.nan)
        seen = np.isfinite(typical).any(axis=1)
        self.typical = np.full(n_blocks, np.inf)
        self.typical[seen] = np.nanmedian(typical[seen], axis=1)

    def defined(self) -> np.ndarray:
        """(n_blocks,) bool: enough pixels and a least residual below _TEXTURED times the median
        over d (a disparity of its own)."""
        return (
            (self.size >= _MIN_BLOCK_SAMPLES)
            & np.isfinite(self.least)
            & (self.least < _TEXTURED * self.typical)
        )

    def resolves(self, b: int) -> bool:
        """Whether block ``b`` tells its disparity from one 2 * SAME_DISPARITY_PX away on
        either side (a shading ramp or a blurred texture matches nearly as well there)."""
        own, dmax = int(self.best[b]), self.mean.shape[1] - 1
        step = 2.0 * SAME_DISPARITY_PX
        return all(
            not self.matches_at(b, int(round(own + s * step)))
            for s in (-1, 1)
            if 0 <= own + s * step <= dmax
        )

    def matches_at(self, b: int, d: int) -> bool:
        """Whether block ``b`` matches at disparity ``d`` (within SAME_DISPARITY_PX) as well as
        at its own best: the mean per-pixel excess residual is under _T_SAME standard errors."""
        lo = max(int(np.ceil(d - SAME_DISPARITY_PX)), 0)
        hi = min(int(np.floor(d + SAME_DISPARITY_PX)), self.mean.shape[1] - 1)
        at = lo + int(np.argmin(self.mean[b, lo : hi + 1]))
        own = int(self.best[b])
        if at == own:
            return True
        rows = self.diff[self.starts[b] : self.starts[b] + self.size[b]]
        x = rows[:, at] - rows[:, own]
        x = x[np.isfinite(x)]
        if len(x) < _MIN_BLOCK_SAMPLES:
            return False
        # Mean excess over its standard error, with the pixels whose partner meets a line
        # (a heavy tail) clipped to 3 robust sigmas.
        med = float(np.median(x))
        spread = 3.0 * 1.4826 * float(np.median(np.abs(x - med))) + 1e-3
        x = np.clip(x, med - spread, med + spread)
        se = float(np.std(x)) / np.sqrt(len(x)) + 1e-6
        return float(np.mean(x)) < _T_SAME * se
