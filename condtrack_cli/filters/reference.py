"""What the CLF and the CNLF share: each point's reference patch, its measurement in the gate, its update.

The search region must be sized before R_k is known: it uses
S = S_pred + R_gate, S_pred the predicted covariance of the point (CLF:
Sigma_{k|k-1}; CNLF: the mixture's second moment) and R_gate the point's last
finite R_k (the configured nominal one before the first), clamped to
[gate_r_min, gate_r_max]. A measurement is used (and the point is visible) when
R_k is finite and z_k lies in the gate nu^T (S_pred + R_k)^-1 nu <= gamma (§3.2),
and its residual, read at the sub-pixel z_k (``Measurement.aligned``: a texture
misaligned by a fraction of a pixel does not inflate it), is at most
``foreign_residual`` times the point's usual one, itself read as at least the
noise's m 2 sigma^2 (issue 31): a match in the gate that fits the reference patch much worse than
the point's own matches have lies on something covering the point (an occluder
that the gate overlaps, or that the point's gate was moved onto), and the point is
covered there (R = inf), whatever the gate's position test says.

A point is reported visible where its measurement is used, and also where its
surface is too flat to measure (R = inf: a weak texture under noise, an edge)
but its best match lies where its last R_k allows from the prediction (the gate's
gamma), fits its reference within ``flat_visible_residual`` times its usual
residual, and a flat patch would not (``shown``, issue 31); or, where that best
match lies farther, when the patch at the prediction itself fits within the same
bound (a flat surface's minimum wanders along its flat direction, the point is
where it was predicted): such a point is not
covered, only not measurable on this frame. A covered point's best match in its
wide gate lies pixels away; the flat-patch test keeps a weak reference, which a
flat part of an occluder fits about as well as its own neighbourhood, from being
shown through it. The filter's state does not see this: the measurement is not
used, and the point counts as not found for every other rule, but for the
fallback gate centres (``measure_in_gate``), which do not search again for a
point shown.

With ``warp_reference`` the reference patch is matched as the scene has deformed it
since it was taken (issue 45): each step's local affine map of the point's
neighbourhood, A_k = I + dU/dx of the local field (``clf.local_dynamics``, eq. 1's
A_k), is accumulated into J = A_k ... A_{r+1} since the re-take r, and the patch
matched is the reference sampled at J^-1 v (v the patch's pixel offsets) from a patch
of side 2t - 1 taken with it (room for a contraction to half). A driving camera's
scene grows by a few per cent a frame, so that a square patch taken a few frames
before no longer matches where the point is: on kt3dmoseg_seq005 (CLF, every
re-take and fallback as shipped, the warp on every point; a one-off diagnosis run,
docs/departures.md) the measurement's median error 8 frames after the query fell
from 1.34 to 1.16 px. The field's Jacobian is noisy on a deforming face
or animal (and a prediction off the point makes any two patches fit alike), so each
point uses the warped patch only where J moves some pixel of it by half a pixel or
more (``WARP_REACH``) but no farther than the wide patch's margin (t // 2 px: J,
accumulated while a point coasts, can grow without bound; beyond the margin the
warped patch is the wide patch's clamped border), and it fits the frame at the
prediction clearly better than the patch as taken (below half its cost,
``WARP_BETTER``): the point's own evidence. With any better fit instead the faces'
dudek_01 fell from 0.841 to 0.818, below LK, and the camel from 0.256 to 0.242
(mean of seeds 0-4; docs/departures.md). The first patch (``anchors``) is warped
the same way, by J since the query, for the drift check's match (``_anchored``) alone,
and only while the point has been found on every frame since its query
(``anchor_held``): after a loss J has run through an occlusion or a spell the point
did not follow, and nothing ties it to the point (warping the first patch wherever it
is matched, the re-acquisition's search after a loss too, lost 0.21 <delta_avg on
dudek_03 and 0.04 on the camel; docs/departures.md, "The first patch warped for the
drift check").
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np

from condtrack_cli.filters import kalman
from condtrack_cli.measure.interface import Measurement, Measurer
from condtrack_cli.measure.surfaces import FrameSums, extract_templates, frame_sums, zero_mean_minima
from condtrack_cli.filters.settings import REACQUIRE_FRAMES, STEADY_FRAMES, MeasuredFilterSettings
from condtrack_cli.types import Frame


def lk_centres(prev: np.ndarray, cur: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(n, 2) positions in frame ``cur`` of (n, 2) points ``xy`` of frame ``prev`` by OpenCV's pyramidal Lucas-Kanade
    on the frames at half resolution (``cv2.pyrDown``; a 13 px window, maxLevel 3: about the reach of the STK
    baseline's 21 px window at maxLevel 3 on the full frames, with a window that spans less of a moving object's
    edge; docs/departures.md), and (n,) bool: found (LK's status, a finite position)."""
    half = (np.asarray(xy, np.float64) / 2).astype(np.float32).reshape(-1, 1, 2)  # pyrDown's (i, j): the frame's (2i, 2j)
    moved, status, _ = cv2.calcOpticalFlowPyrLK(  # the STK baseline's criteria (``filters/stk.py``)
        prev, cur, half, None, winSize=(13, 13), maxLevel=3,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01), minEigThreshold=1e-4,
    )
    moved, ok = moved.reshape(-1, 2).astype(np.float64), status.reshape(-1).astype(bool)
    return moved * 2, ok & np.isfinite(moved).all(axis=1)


COARSE_SIDE = 13  #: side of the coarse search's patch at half resolution (px; 26 px of the full frame)
COARSE_REACH = 40  #: half-side of the coarse search's square at half resolution (px; 80 px of the full frame)
#: Half-side (px) of the full-resolution search around a re-acquisition's centre: that centre is its patch's best
#: match on the half-resolution grid, within a pixel of it there (2 px of the frame) when it is the point
REACQUIRE_REACH = 3
#: A lost point's match there is used only where it fits the reference within this many times its usual residual
REACQUIRE_FIT = 2.5
#: A lost point is searched for only where its reference's texture, its cost against a flat patch (``flat_cost``), is
#: above this many times the noise's m 2 sigma^2: the search compares its patch with every candidate of its square,
#: (2 ``COARSE_REACH`` + 1)^2 of them, and a patch about as flat as the noise is matched as well by any flat one
#: (bench/history.md, "Eleventh round")
REACQUIRE_TEXTURE = 3.0
#: ``warp_reference``: the warp is applied only where it moves some pixel of the patch by at least this much (px) ...
WARP_REACH = 0.5
#: ... and used only where its fit at the prediction is below this share of the patch as taken's (``lk_better``'s
#: "clearly better"): a noisy field's warp, or a prediction off the point, makes the two fits alike
WARP_BETTER = 0.5


class HalfFrame:
    """A frame at half resolution (``cv2.pyrDown``: its (i, j) is the frame's (2i, 2j)): ``image`` as the frame's
    (uint8, for Lucas-Kanade), ``gray`` float32, and the window sums of the coarse search, computed on first use."""

    def __init__(self, image: np.ndarray):
        self.image, self.gray = image, image.astype(np.float32)
        self._sums: FrameSums | None = None

    @property
    def sums(self) -> FrameSums:
        """:func:`frame_sums` of ``COARSE_SIDE`` px windows for the zero-mean cost."""
        if self._sums is None:
            self._sums = frame_sums(self.gray, COARSE_SIDE, "zero_mean")
        return self._sums


def coarse_centres(prev: HalfFrame, cur: HalfFrame, xy: np.ndarray) -> np.ndarray:
    """(n, 2) where the patches of (n, 2) points ``xy`` of frame ``prev`` are found in frame ``cur`` by an exhaustive
    search at half resolution (px of the full frame, to about 2 px).

    Each point's ``COARSE_SIDE`` px patch of ``prev`` is compared, by the zero-mean SSD (:func:`ssd_surfaces`,
    ``measure.cost``'s default, whatever the run's cost), with every patch of ``cur`` whose centre lies within
    ``COARSE_REACH`` px of its own, and the best is kept: a search that needs no prediction at all, for the points
    that neither the dynamics nor the other fallback centres find.
    """
    return coarse_search(extract_templates(prev.gray, np.asarray(xy, np.float64) / 2, COARSE_SIDE), cur, xy)


def coarse_search(patches: np.ndarray, cur: HalfFrame, xy: np.ndarray) -> np.ndarray:
    """(n, 2) the best match (px of the full frame) in the half-resolution frame ``cur`` of (n, COARSE_SIDE,
    COARSE_SIDE) half-resolution ``patches`` among the patches centred within ``COARSE_REACH`` px (half resolution)
    of (n, 2) full-frame positions ``xy``; the zero-mean SSD."""
    centres = np.rint(np.asarray(xy, np.float64) / 2).astype(np.intp)
    row, col = np.divmod(zero_mean_minima(cur.gray, patches, centres, COARSE_REACH, cur.sums), 2 * COARSE_REACH + 1)
    return (centres + np.stack([col, row], axis=1) - COARSE_REACH) * 2.0


def searched(measure: Measurer, predicted: np.ndarray, gate_cov: np.ndarray, xy: np.ndarray, gamma: float) -> np.ndarray:
    """(n,) bool: the search around (n, 2) ``predicted`` with gate covariance (n, 2, 2) ``gate_cov`` held the candidate
    nearest to (n, 2) ``xy``: the stage's own ``searched`` where it has one, else the gate ellipse of threshold gamma."""
    if hasattr(measure, "searched"):
        return measure.searched(predicted, gate_cov, xy)
    with np.errstate(invalid="ignore"):
        return ~(kalman.mahalanobis2(xy - predicted, gate_cov) > gamma)


def _square_gate(reach: float, n: int, gamma: float) -> np.ndarray:
    """(n, 2, 2) the gate covariance whose search square has half-side ``reach`` px (``ssd._half_sizes``:
    ceil(sqrt(gamma lambda_max)) = ``reach`` for an integer ``reach``) for a gate threshold ``gamma``."""
    return np.repeat(np.eye(2)[None] * (reach**2 / gamma), n, axis=0)


def _fit(m: Measurement) -> np.ndarray:
    """(n,) how well each match fits its reference, as the residual tests read it: the cost at the sub-pixel z_k
    where the stage gives it (``Measurement.aligned``), else at the integer minimum."""
    return m.residual if m.aligned is None else m.aligned


#: Weight of a match's residual in its point's usual residual (``ReferenceMatcher.usual``): about 3 frames' memory.
USUAL_WEIGHT = 1.0 / 3.0


class _Attempt(NamedTuple):
    """Matches to try around one centre per point (:meth:`ReferenceMatcher._attempt`)."""

    tried: np.ndarray  #: (k,) the points, indices into the step's
    centre: np.ndarray  #: (k, 2) the centre of each point's search (px)
    templates: np.ndarray  #: (k, t, t) the patches matched
    rival: np.ndarray  #: (k,) the residual a match must be clearly below (``lk_better``; NaN: none)
    anchor: bool  #: the patches are the points' first ones, taken back where used


@dataclass(frozen=True)
class GatedMeasurement:
    """A measurement of n points: z (n, 2), R (n, 2, 2) raw (inf where uninformative),
    R_used (n, 2, 2) finite (identity where R is inf), valid (n,) bool, residual (n,), shown (n,) bool:
    valid, or unmeasurable but fitting its reference (module docstring), shift (n, 2): where the match was made
    around the fallback centre (``lk_fallback``), that centre minus the prediction, else 0; jump (n, 2): where the
    match is the re-acquisition's (:meth:`ReferenceMatcher._reacquire`), z minus the prediction, else 0 (px)."""

    z: np.ndarray
    R: np.ndarray
    R_used: np.ndarray
    valid: np.ndarray
    residual: np.ndarray
    shown: np.ndarray
    shift: np.ndarray  #: (n, 2) the move of the prediction to the fallback gate centre (0: none)
    jump: np.ndarray  #: (n, 2) the re-acquisition's move of the point from its prediction (0: none)

    @property
    def seen_unmeasured(self) -> np.ndarray:
        """(n,) bool: shown but not used (``Tracker.seen_unmeasured``)."""
        return self.shown & ~self.valid


class ReferenceMatcher:
    """Reference patches of P points and their gated measurement (paper §5.2, §3.2)."""

    def __init__(self, measure: Measurer, settings: MeasuredFilterSettings, n_points: int, gamma: float):
        """measure: the measurement stage; gamma: the gate's threshold on nu^T S^-1 nu (``measure.gamma``)."""
        self.measure, self.settings, self.gamma = measure, settings, gamma
        t = measure.template_side
        #: the pixel count of the measurement's noise (``Measurer.pixel_count``; t^2 for a stage without it)
        self.pixel_count = float(getattr(measure, "pixel_count", t * t))
        self.templates = np.zeros((n_points, t, t), np.float32)
        #: (P, t, t) each point's first reference patch, taken at its query
        self.anchors = np.zeros((n_points, t, t), np.float32)
        #: the measurement at ``drift_check_template`` px (the stage's own without it or without ``resized``), and
        #: (P, a, a) each point's first patch at its side a, taken at its query: the anchor of ``drift_check``
        resized = getattr(measure, "resized", None)
        side = settings.drift_check_template
        self.anchor_measure = resized(side) if side is not None and resized is not None else measure
        side = self.anchor_measure.template_side
        self.drift_anchors = np.zeros((n_points, side, side), np.float32) if side != t else self.anchors
        #: (P, 2t - 1, 2t - 1) the reference and first patches with the room a warp samples (``warp_reference``)
        self.wide = np.zeros((n_points, 2 * t - 1, 2 * t - 1), np.float32)
        self.anchor_wide = np.zeros_like(self.wide)
        #: (P, 2, 2) J: the local field's linear maps accumulated since each reference was taken (``warp_reference``)
        self.warp = np.repeat(np.eye(2)[None], n_points, axis=0)
        #: (P, 2, 2) the same maps accumulated since each point's query, and (P,) whether the point has been found on
        #: every frame since: where the drift check's first patch is matched warped (``_anchored``)
        self.anchor_warp = np.repeat(np.eye(2)[None], n_points, axis=0)
        self.anchor_held = np.ones(n_points, bool)
        #: (P,) least per-axis variance of the offset of each point's reference re-taken on the last step (px^2):
        #: r^2 / 4, the per-axis variance of an offset spread evenly over the disk of radius r, with r = ``drift_check``
        #: where the first patch was not found within ``drift_check`` px of the estimate and r = the distance from the
        #: estimate to the first patch's match where it was (the re-take is there); 0 where no reference was re-taken
        self.offset_floor = np.zeros(n_points)
        self.gate_r = np.repeat(settings.nominal_r * np.eye(2)[None], n_points, axis=0)
        self.noise_sigma: float | None = None
        #: (P,) each point's usual residual (grey levels^2): the mean of the residuals of its matches used, each
        #: weighing ``USUAL_WEIGHT`` against the mean before it (NaN before its first match)
        self.usual = np.full(n_points, np.nan)
        #: (P,) the matching cost of each reference patch against a flat patch at its mean (grey levels^2)
        self.flat_cost = np.full(n_points, np.nan)
        #: (P, 2) each point's last step between two frames it was found on (px/frame; NaN: not found on both)
        self.step = np.full((n_points, 2), np.nan)
        #: (P, 2) where each point was last found (px) and (P, COARSE_SIDE, COARSE_SIDE) its patch there at half
        #: resolution, with ``lk_fallback`` (the re-acquisition's, :meth:`_reacquire`)
        self.last_seen = np.full((n_points, 2), np.nan)
        self.last_patch = np.zeros((n_points, COARSE_SIDE, COARSE_SIDE), np.float32)
        #: (P, COARSE_SIDE, COARSE_SIDE) each point's patch at its query at half resolution, with ``lk_fallback``
        #: (the re-acquisition's second search, :meth:`_reacquire`)
        self.anchor_half = np.zeros((n_points, COARSE_SIDE, COARSE_SIDE), np.float32)
        #: (P,) whether each point's reference was taken where its first patch vouched for it: at its query, at a
        #: re-take the first patch confirmed (``_anchored``), or the first patch itself taken back (:meth:`_reacquire`)
        self.vouched = np.zeros(n_points, bool)
        #: (P, 2) where each point was last found with a vouched reference (px), with ``lk_fallback``: the centre of
        #: the re-acquisition's first-patch search (:meth:`_reacquire`)
        self.vouched_seen = np.full((n_points, 2), np.nan)
        #: (P,) the frames each point has been found on in a row, and (P, 2) where it was last found with a vouched
        #: reference after ``STEADY_FRAMES`` such frames (px), with ``lk_fallback``: the centre of the
        #: re-acquisition's last first-patch search (:meth:`_reacquire`)
        self.found_run = np.zeros(n_points, np.int64)
        self.steady_seen = np.full((n_points, 2), np.nan)
        self._halves: list[tuple[np.ndarray, HalfFrame]] = []  #: (image, its :class:`HalfFrame`) of recent frames

    def start(self, index: np.ndarray, frame: Frame, xy: np.ndarray) -> None:
        """Take the reference patches of points ``index`` at (n, 2) ``xy`` in their query frame."""
        if self.noise_sigma is None:
            self.noise_sigma = self.measure.noise_sigma(frame.gray)
        self._take(index, self.measure.templates(frame.gray, xy), self._wide_patches(frame, xy))
        self.anchors[index] = self.templates[index]
        self.anchor_wide[index] = self.wide[index]
        self.anchor_warp[index] = np.eye(2)
        self.anchor_held[index] = True
        if self.drift_anchors is not self.anchors:
            self.drift_anchors[index] = self.anchor_measure.templates(frame.gray, xy)
        self.usual[index] = np.nan
        self.step[index] = np.nan
        self._remember(index, frame, xy)
        self.vouched[index] = True
        if self.settings.lk_fallback:
            self.anchor_half[index] = self.last_patch[index]
            self.vouched_seen[index] = xy
            self.steady_seen[index] = xy
            self.found_run[index] = 0

    def _take(self, index: np.ndarray, patches: np.ndarray, wide: np.ndarray | None) -> None:
        """Points ``index`` take the (n, t, t) ``patches`` as their reference, with ``warp_reference`` the (n, 2t - 1,
        2t - 1) ``wide`` patches around them and J reset to the identity (``wide`` unused without); their
        ``flat_cost`` with them."""
        self.templates[index] = patches
        if self.settings.warp_reference:
            self.wide[index] = wide
            self.warp[index] = np.eye(2)
        flat = np.broadcast_to(patches.mean(axis=(1, 2), keepdims=True), patches.shape)
        self.flat_cost[index] = self.measure.cost(patches, np.ascontiguousarray(flat, np.float32))

    def _wide_patches(self, frame: Frame, xy: np.ndarray) -> np.ndarray | None:
        """(n, 2t - 1, 2t - 1) patches of ``frame`` at (n, 2) ``xy`` with ``warp_reference`` (None without)."""
        return extract_templates(frame.gray, xy, self.wide.shape[1]) if self.settings.warp_reference else None

    def deform(self, index: np.ndarray, linear: np.ndarray) -> None:
        """With ``warp_reference``: the neighbourhoods of points ``index`` were moved this step by local affine maps
        with (n, 2, 2) linear parts ``linear`` (A_k of eq. 1); J <- A_k J, and the first patch's J likewise."""
        if self.settings.warp_reference:
            self.warp[index] = np.einsum("nij,njk->nik", linear, self.warp[index])
            self.anchor_warp[index] = np.einsum("nij,njk->nik", linear, self.anchor_warp[index])

    def _references(self, index: np.ndarray, frame: Frame, predicted: np.ndarray) -> np.ndarray:
        """(n, t, t) the patches points ``index`` are matched with: their reference, or with ``warp_reference`` the
        reference warped by J (module docstring) where J moves some pixel by ``WARP_REACH`` px or more, and by no more
        than the wide patch's margin, and the warped patch fits ``frame``'s patch at (n, 2) ``predicted`` clearly
        better (``WARP_BETTER``)."""
        plain = self.templates[index]
        if not self.settings.warp_reference:
            return plain
        return self._warped(plain, self.wide[index], self.warp[index], frame, predicted)

    def _warped(self, plain: np.ndarray, wide_patches: np.ndarray, warp: np.ndarray, frame: Frame,
                predicted: np.ndarray) -> np.ndarray:
        """(n, t, t) ``plain`` patches, each replaced by its (n, 2t - 1, 2t - 1) ``wide_patches`` sampled at J^-1 v
        (J the (n, 2, 2) ``warp``) where J moves some pixel by ``WARP_REACH`` px or more, and by no more than the wide
        patch's margin, and the warped patch fits ``frame``'s patch at (n, 2) ``predicted`` clearly better
        (``WARP_BETTER``)."""
        t, side = plain.shape[1], wide_patches.shape[1]
        inverse = np.linalg.inv(warp)  # (n, 2, 2): the warped patch's pixel v samples the reference at J^-1 v
        reach = (t // 2) * np.abs(inverse - np.eye(2)).sum(axis=2).max(axis=1)  # a corner pixel's largest x or y shift
        room = (side - t) // 2  # a warp that samples beyond the wide patch is not represented: not applied
        moved = np.flatnonzero((reach >= WARP_REACH) & (reach <= room) & np.isfinite(predicted).all(axis=1))
        if not moved.size:
            return plain
        offsets = np.arange(t, dtype=np.float64) - t // 2
        vx, vy = offsets[None, None, :], offsets[None, :, None]  # each pixel's (x, y) offset, (1, t, t) by broadcast
        moved_inverse = inverse[moved][:, :, :, None, None]  # (m, 2, 2, 1, 1)
        centre = side // 2
        # (m, t, t): where J^-1 v falls in the wide patch, clamped to it
        sx = np.clip(moved_inverse[:, 0, 0] * vx + moved_inverse[:, 0, 1] * vy + centre, 0, side - 1)
        sy = np.clip(moved_inverse[:, 1, 0] * vx + moved_inverse[:, 1, 1] * vy + centre, 0, side - 1)
        cx, cy = (np.minimum(np.floor(source).astype(np.intp), side - 2) for source in (sx, sy))
        fx, fy = sx - cx, sy - cy
        at = (np.arange(moved.size)[:, None, None] * side + cy) * side + cx  # the top-left neighbour, flat index
        wide = wide_patches[moved].reshape(-1)
        warped = ((wide[at] * (1 - fx) + wide[at + 1] * fx) * (1 - fy)
                  + (wide[at + side] * (1 - fx) + wide[at + side + 1] * fx) * fy).astype(np.float32)
        there = self.measure.templates(frame.gray, predicted[moved])
        better = self.measure.cost(warped, there) < WARP_BETTER * self.measure.cost(plain[moved], there)
        chosen = plain.copy()
        chosen[moved[better]] = warped[better]
        return chosen

    def measure_in_gate(self, index: np.ndarray, frame: Frame, predicted: np.ndarray, s_pred: np.ndarray,
                        prev: Frame | None = None, x_prev: np.ndarray | None = None,
                        retry: np.ndarray | None = None, lost_for: np.ndarray | None = None) -> GatedMeasurement:
        """Match points ``index`` around (n, 2) ``predicted`` with predicted covariance (n, 2, 2) ``s_pred``.

        With ``lk_fallback`` and the previous frame ``prev``, the points of (n,) bool ``retry`` (found on ``prev``
        at (n, 2) ``x_prev``) whose match is not used, and not shown (module docstring: the point is there, its
        surface flat), are matched again around other gate centres, in turn (:meth:`_fallback`): where pyramidal
        Lucas-Kanade moves them from ``x_prev`` (:func:`lk_centres`), where their last measured step carries
        them (``step``), then where a coarse search finds their patch (:func:`coarse_centres`), each when it lies
        outside the gate just searched (:func:`searched`), with the same covariance and the same tests, and used
        only if its residual is below ``lk_better`` times the best one of the gate around the prediction. Where
        that match is used, the prediction is moved to that centre: ``shift`` (n, 2), the displacement the filter
        adds to its prediction (0 elsewhere). On the card scene's entry they find the card's points that the local
        field loses; on the shared real sets they move <delta_avg by at most 0.013 (docs/departures.md). With
        ``lk_fallback`` and (n,) ``lost_for``, the frames since each point was last found (the error model's
        ``coasted``), the points lost for 1 to ``REACQUIRE_FRAMES`` frames and predicted inside the frame are then
        searched for around where they were last found (:meth:`_reacquire`); a point predicted outside the frame
        has left it with the motion around it (on KITTI such points were a large share of the searches:
        bench/history.md, "Speed since 35ed7c7").
        """
        m, r_used, valid = self._gated(index, frame, predicted, s_pred)
        s = self.settings
        usual = self.usual[index]
        shown = valid.copy()
        if s.flat_visible_residual is not None:  # NaN residuals (no match) and usual residuals compare False
            bound = s.flat_visible_residual * self._yardstick(index)
            near = kalman.mahalanobis2(m.z - predicted, self.gate_r[index]) <= self.gamma  # NaN z: False
            textured = self.flat_cost[index] > bound
            shown |= ~m.informative & near & (_fit(m) <= bound) & textured
            flat = np.flatnonzero(~m.informative & ~shown & textured)
            if flat.size:
                at_prediction = self.measure.templates(frame.gray, predicted[flat])
                shown[flat] = self.measure.cost(self.templates[index[flat]], at_prediction) <= bound[flat]
        shift = np.zeros_like(predicted)
        height, width = frame.image.shape
        inside = (predicted >= 0).all(axis=1) & (predicted[:, 0] <= width - 1) & (predicted[:, 1] <= height - 1)
        if s.lk_fallback and prev is not None and retry is not None:
            tried = np.flatnonzero(retry & ~shown & np.isfinite(x_prev).all(axis=1) & inside)
            if tried.size:
                m, r_used = self._fallback(index, tried, frame, prev, x_prev, predicted, s_pred, m, r_used, valid,
                                           shown, shift)
        jump = np.zeros_like(predicted)
        if s.lk_fallback and prev is not None and lost_for is not None:
            lost = np.flatnonzero(~shown & (lost_for >= 1) & (lost_for <= REACQUIRE_FRAMES) & inside)
            if lost.size:
                m, r_used = self._reacquire(index, lost, frame, predicted, s_pred, m, r_used, valid, shown, shift)
                found_again = lost[shown[lost]]
                jump[found_again] = m.z[found_again] - predicted[found_again]
        if s.foreign_residual is not None or s.flat_visible_residual is not None:
            fit = _fit(m)[valid]
            self.usual[index[valid]] = np.where(np.isnan(usual[valid]), fit,
                                                usual[valid] + USUAL_WEIGHT * (fit - usual[valid]))
        clamped = np.clip(r_used, -s.gate_r_max, s.gate_r_max)
        clamped[:, [0, 1], [0, 1]] = np.clip(r_used[:, [0, 1], [0, 1]], s.gate_r_min, s.gate_r_max)
        self.gate_r[index[valid]] = clamped[valid]
        return GatedMeasurement(m.z, m.R, r_used, valid, m.residual, shown, shift, jump)

    def _fallback(self, index: np.ndarray, tried: np.ndarray, frame: Frame, prev: Frame, x_prev: np.ndarray,
                  predicted: np.ndarray, s_pred: np.ndarray, m: Measurement, r_used: np.ndarray, valid: np.ndarray,
                  shown: np.ndarray, shift: np.ndarray) -> tuple[Measurement, np.ndarray]:
        """``measure_in_gate``'s fallback for the points ``tried`` (indices into ``index``): the measurement ``m``
        and (n, 2, 2) ``r_used`` with the matches won around the fallback centres (new arrays where any is won);
        (n,) ``valid``, ``shown`` and (n, 2) ``shift`` are updated in place.

        The centres, each tried on the points that the ones before did not win: where Lucas-Kanade moves the
        point from ``x_prev`` (:func:`lk_centres`), ``x_prev`` plus the point's last measured step (``step``; a
        constant velocity: an object that entered the frame at 40-50 px a frame and goes on, which neither the
        local field nor Lucas-Kanade follows where the object's edge fills the window), then the best match of
        an exhaustive search at half resolution (:func:`coarse_centres`; a point with no measured step yet).
        """
        lk, lk_found = lk_centres(self._half(prev).image, self._half(frame).image, x_prev[tried])
        constant_step = x_prev[tried] + self.step[index[tried]]
        for centre, usable in ((lk, lk_found), (constant_step, np.isfinite(constant_step).all(axis=1))):
            usable &= ~shown[tried]  # not won by an earlier centre
            m, r_used = self._match_around(index, tried[usable], centre[usable], frame, predicted, s_pred, m,
                                           r_used, valid, shown, shift)
        left = tried[~shown[tried]]
        if left.size:
            centre = coarse_centres(self._half(prev), self._half(frame), x_prev[left])
            m, r_used = self._match_around(index, left, centre, frame, predicted, s_pred, m, r_used, valid, shown,
                                           shift)
        return m, r_used

    def _match_around(self, index: np.ndarray, tried: np.ndarray, centre: np.ndarray, frame: Frame,
                      predicted: np.ndarray, s_pred: np.ndarray, m: Measurement, r_used: np.ndarray,
                      valid: np.ndarray, shown: np.ndarray, shift: np.ndarray) -> tuple[Measurement, np.ndarray]:
        """:meth:`_fallback` around one (n, 2) ``centre`` per point of ``tried``, with the reference in the gate;
        returns and updates as it does: :meth:`_match_attempts` of the one :meth:`_attempt`."""
        attempt = self._attempt(index, tried, centre, frame, predicted, s_pred, m, False)
        return self._match_attempts(index, [attempt], frame, predicted, s_pred, m, r_used, valid, shown, shift)

    def _attempt(self, index: np.ndarray, tried: np.ndarray, centre: np.ndarray, frame: Frame,
                 predicted: np.ndarray, s_pred: np.ndarray, m: Measurement, anchor: bool) -> _Attempt:
        """The matches to try around (n, 2) ``centre``, one per point of ``tried`` (indices into ``index``), given
        the gate's measurement ``m``: a centre inside the gate is dropped (it was searched there already, with the
        same patch), except with ``anchor``, where the patch matched is the point's first one (``anchors``), which
        is compared with its own fit where the gate's match lies: the match must fit clearly better than that rival
        (``lk_better``; NaN: none), the reference's best residual in the gate without ``anchor``."""
        if anchor:
            return _Attempt(tried, centre, self.anchors[index[tried]],
                            self._first_patch_cost(index[tried], frame, m.z[tried]), True)
        ok = ~searched(self.measure, predicted[tried], s_pred[tried] + self.gate_r[index[tried]], centre, self.gamma)
        tried, centre = tried[ok], centre[ok]
        return _Attempt(tried, centre, self._references(index[tried], frame, centre), m.residual[tried], False)

    def _match_attempts(self, index: np.ndarray, attempts: list[_Attempt], frame: Frame, predicted: np.ndarray,
                        s_pred: np.ndarray, m: Measurement, r_used: np.ndarray, valid: np.ndarray,
                        shown: np.ndarray, shift: np.ndarray, fit_bound: float | None = None,
                        reach: int | None = None) -> tuple[Measurement, np.ndarray]:
        """Match the ``attempts`` (:meth:`_attempt`), all in one measurement, and use them in turn: a point's match
        is used where it passes the gate's tests and its attempt's rival, and where no earlier attempt won the
        point. Returns the measurement ``m`` and (n, 2, 2) ``r_used`` with the matches used (new arrays where any
        is); (n,) ``valid``, ``shown`` and (n, 2) ``shift`` are updated in place; an anchor attempt's points whose
        match is used take their first patch back as their reference.

        fit_bound: a match is used only where it fits the reference within this many times the usual residual;
        reach: the search's half-side around each centre (px; None: the gate's, as around the prediction). With a
        ``reach``, the points whose least residual in that square (``least_residuals``, where the stage has it) is
        already at least ``lk_better`` times the rival's are not matched further: their match could not be used
        (most of the re-acquisition's matches on KITTI: bench/history.md, "Eighth round"), and the others' is the
        same. With one half-size for every point a point's measurement does not depend on the points measured with
        it (``least_residuals``), so that attempts measured together match as each alone would; with the gate's
        half-sizes they may not (their last bits), and the caller gives one attempt."""
        tried = np.concatenate([a.tried for a in attempts])
        if not tried.size:
            return m, r_used
        centre = np.concatenate([a.centre for a in attempts])
        templates = np.concatenate([a.templates for a in attempts])
        rival = np.concatenate([a.rival for a in attempts])
        attempt = np.repeat(np.arange(len(attempts)), [len(a.tried) for a in attempts])
        if reach is not None and hasattr(self.measure, "least_residuals"):
            least = self.measure.least_residuals(frame.gray, templates, centre,
                                                 _square_gate(reach, len(tried), self.gamma))
            may_win = ~(least >= self.settings.lk_better * rival)
            tried, centre, templates = tried[may_win], centre[may_win], templates[may_win]
            rival, attempt = rival[may_win], attempt[may_win]
            if not tried.size:
                return m, r_used
        m2, r2, valid2 = self._gated(index[tried], frame, centre, s_pred[tried], templates, reach)
        valid2 &= ~(m2.residual >= self.settings.lk_better * rival)
        if fit_bound is not None:
            valid2 &= _fit(m2) <= fit_bound * self._yardstick(index[tried])
        for number, anchor in enumerate(a.anchor for a in attempts):
            usable = valid2 & (attempt == number) & ~shown[tried]  # not won by an earlier attempt
            won = tried[usable]
            if not won.size:
                continue
            if anchor:
                self._take(index[won], self.anchors[index[won]], self.anchor_wide[index[won]])
                self.vouched[index[won]] = True
            m = Measurement(*(np.array(array, copy=True) for array in (m.z, m.R, m.residual, m.informative,
                                                                      _fit(m))))
            m.z[won], m.R[won] = m2.z[usable], m2.R[usable]
            m.residual[won], m.informative[won] = m2.residual[usable], m2.informative[usable]
            m.aligned[won] = _fit(m2)[usable]
            r_used = r_used.copy()
            r_used[won], valid[won], shown[won] = r2[usable], True, True
            shift[won] = centre[usable] - predicted[won]
        return m, r_used

    def _first_patch_cost(self, index: np.ndarray, frame: Frame, xy: np.ndarray) -> np.ndarray:
        """(n,) the cost of the first reference patches of points ``index`` against ``frame``'s patches at (n, 2)
        ``xy`` (grey levels^2; NaN where ``xy`` is NaN)."""
        cost = np.full(len(index), np.nan)
        at = np.flatnonzero(np.isfinite(xy).all(axis=1))
        if at.size:
            cost[at] = self.measure.cost(self.anchors[index[at]], self.measure.templates(frame.gray, xy[at]))
        return cost

    def _remember(self, index: np.ndarray, frame: Frame, xy: np.ndarray) -> None:
        """With ``lk_fallback``: record that points ``index`` were last found on ``frame`` at (n, 2) ``xy``, and their
        patch there at half resolution."""
        if self.settings.lk_fallback:
            self.last_seen[index] = xy
            self.last_patch[index] = extract_templates(self._half(frame).gray, xy / 2, COARSE_SIDE)

    def _reacquire(self, index: np.ndarray, lost: np.ndarray, frame: Frame, predicted: np.ndarray,
                   s_pred: np.ndarray, m: Measurement, r_used: np.ndarray, valid: np.ndarray, shown: np.ndarray,
                   shift: np.ndarray) -> tuple[Measurement, np.ndarray]:
        """``measure_in_gate``'s re-acquisition of the points ``lost`` (indices into ``index``: lost for 1 to
        ``REACQUIRE_FRAMES`` frames, not shown): their last patch at half resolution is searched within
        ``COARSE_REACH`` of where they were last found (:func:`coarse_search`: an occluder that carried their
        prediction away, a head turned under a hand), and its best match is a gate centre as the fallback's
        (:meth:`_match_around`), used only where that match fits the reference within ``REACQUIRE_FIT`` times the
        point's usual residual. The points that this does not find are found, if at all, by their first patch
        (``anchor_half``), searched for in the same square and matched there with their first reference patch
        (``anchors``) under the same bound: a point dragged onto an occluder before it was lost was last found, and
        its reference last re-taken, on the occluder, while its first patch is still the point's. Where the point was
        last found with a reference its first patch vouched for (``vouched_seen``: its query, a re-take the drift
        check confirmed, or its first patch taken back) lies more than 2 px from where it was last found, its first
        patch is searched for in that square too, after the first: an occluder may have dragged the point farther
        than the search's reach before it was lost (dudek_03, where a hand sweeping over the face drags a point 100
        px before it is lost: docs/departures.md). Where the point was last found with a vouched reference after
        ``STEADY_FRAMES`` found frames in a row (``steady_seen``) lies more than 2 px from both those centres, its first
        patch is searched for there too, last: found on an occluder's edge for a frame or two between losses, under a
        re-take the drift check confirmed there, the point had its ``vouched_seen`` dragged as well. Those matches must
        also fit the first patch clearly better (``lk_better``) than the first patch fits where the gate's match
        lies (the reference, re-taken on the occluder, fits the occluder well there). Where that match is used the
        point takes its first patch back as its reference. The searches, and their matches, are made for every
        lost point at once (:meth:`_match_attempts`: a first patch's match of a point that an earlier attempt found
        is not used): each measurement's fixed cost is paid once, for the first-patch searches of the few points
        the last patch finds (bench/history.md, "Ninth round"). Updates as :meth:`_fallback`.

        The full-resolution match is made within ``REACQUIRE_REACH`` px of the search's result (where the search found
        the point, within a pixel of it on the half-resolution grid), not in the point's gate, which grows while it
        coasts up to ``search_max``: nearly the same points are found again, at a fraction of the cost
        (bench/history.md, "Speed since 35ed7c7").

        A point with no usual residual (never matched since its query: a patch flatter than the noise, a query on
        what is already covered) is not searched for: its yardstick is NaN, so that no match could pass the
        ``REACQUIRE_FIT`` bound (how many of KITTI's searches that was: bench/history.md, "Ninth round"). Nor is a
        point whose reference is about as flat as the noise (``REACQUIRE_TEXTURE``): most of the 640 x 480 speed
        scene's searches, a few of the shared real sets' and none of their finds (counted with a one-off log:
        bench/history.md, "Eleventh round")."""
        lost = lost[np.isfinite(self._yardstick(index[lost]))
                    & (self.flat_cost[index[lost]] > REACQUIRE_TEXTURE * self._noise_ssd())]
        if not lost.size:
            return m, r_used
        seen, vouched = self.last_seen[index[lost]], self.vouched_seen[index[lost]]
        steady = self.steady_seen[index[lost]]
        elsewhere = np.flatnonzero(np.abs(vouched - seen).max(axis=1) > 2)  # the search's grain: 2 px
        steady_apart = np.flatnonzero((np.abs(steady - seen).max(axis=1) > 2)
                                      & (np.abs(steady - vouched).max(axis=1) > 2))
        anchor_half = self.anchor_half[index[lost]]
        found = coarse_search(np.concatenate([self.last_patch[index[lost]], anchor_half, anchor_half[elsewhere],
                                              anchor_half[steady_apart]]),
                              self._half(frame), np.concatenate([seen, seen, vouched[elsewhere], steady[steady_apart]]))
        count, more = len(lost), 2 * len(lost) + len(elsewhere)
        attempts = [self._attempt(index, lost, found[:count], frame, predicted, s_pred, m, False),
                    self._attempt(index, lost, found[count : 2 * count], frame, predicted, s_pred, m, True),
                    self._attempt(index, lost[elsewhere], found[2 * count : more], frame, predicted, s_pred, m, True),
                    self._attempt(index, lost[steady_apart], found[more:], frame, predicted, s_pred, m, True)]
        return self._match_attempts(index, attempts, frame, predicted, s_pred, m, r_used, valid, shown, shift,
                                    REACQUIRE_FIT, REACQUIRE_REACH)

    def _half(self, frame: Frame) -> HalfFrame:
        """``frame`` at half resolution, kept for the last two frames asked (a frame is the current one, then the
        previous one; ``auto``'s two filters ask for the same pair)."""
        for image, half in self._halves:
            if image is frame.image:
                return half
        half = HalfFrame(cv2.pyrDown(frame.image))
        self._halves = [self._halves[-1], (frame.image, half)] if self._halves else [(frame.image, half)]
        return half

    def _gated(self, index: np.ndarray, frame: Frame, predicted: np.ndarray, s_pred: np.ndarray,
               templates: np.ndarray | None = None, reach: int | None = None
               ) -> tuple[Measurement, np.ndarray, np.ndarray]:
        """The measurement of points ``index`` in the gate around (n, 2) ``predicted`` (S_pred (n, 2, 2) ``s_pred``),
        its R_used (n, 2, 2) and (n,) bool whether it is used (the gate's position test, the residual test);
        templates: the (n, t, t) patches matched (None: their references, :meth:`_references`); reach: search only
        the square of this half-side (px) around ``predicted`` (None: the gate's square, sized from S_pred + R_gate)."""
        if templates is None:
            templates = self._references(index, frame, predicted)
        search = s_pred + self.gate_r[index] if reach is None else _square_gate(reach, len(index), self.gamma)
        m = self.measure.measure(frame.gray, templates, predicted, search, self.noise_sigma)
        r_used = np.where(m.informative[:, None, None], m.R, np.eye(2))
        nu = np.where(m.informative[:, None], m.z - predicted, 0.0)
        valid = m.informative & (kalman.mahalanobis2(nu, s_pred + r_used) <= self.gamma)
        if self.settings.foreign_residual is not None:
            valid &= ~(_fit(m) > self.settings.foreign_residual * self._yardstick(index))  # False without a usual one
        return m, r_used, valid

    def _yardstick(self, index: np.ndarray) -> np.ndarray:
        """(n,) the residual a match of points ``index`` is compared with: their usual one, at least the noise's
        expectation m 2 sigma^2 (m template pixels; a sub-pixel match's residual falls to it); NaN before the first
        (``np.maximum`` keeps it), where every bound on it fails."""
        return np.maximum(self.usual[index], self._noise_ssd())

    def _noise_ssd(self) -> float:
        """m 2 sigma^2: the SSD two patches of m template pixels show from the acquisition noise (sigma) alone."""
        return self.pixel_count * 2 * self.noise_sigma**2

    def refresh(
        self, index: np.ndarray, prev: Frame, x_prev: np.ndarray, frame: Frame, x_post: np.ndarray,
        found_before: np.ndarray, measured: GatedMeasurement,
    ) -> np.ndarray:
        """Reference update (paper §5.2): re-take the reference patch at the posterior position ``x_post``.

        With m template pixels and sigma the acquisition noise, m 2 sigma^2 is the
        SSD expected from noise alone. A point's reference is refreshed when
        (1) it was found this frame and the previous one (``found_before``; finite
        R_k in the gate), (2) its residual r_k(z_k) exceeds ``update_residual``
        m 2 sigma^2: the patch has drifted away from the reference, and (3) the
        change was gradual: the SSD between the new patch and the patch at the
        previous estimate ``x_prev`` in the previous frame is at most
        ``update_abruptness`` r_k(z_k), i.e. the drift did not all happen since the
        last frame. An occluder edge creeping over a clean patch makes nearly the
        whole residual appear in one frame and fails (3); a whole occluder fails
        (1). x_prev, x_post: (n, 2); found_before: (n,) bool. Returns (n,) bool: re-taken.
        Also records each point's ``step`` x_post - x_prev where it was found on both frames (NaN elsewhere),
        the fallback's constant-step centre, and where and how it was last found (:meth:`_remember`).
        """
        s = self.settings
        self.step[index] = np.where((found_before & measured.valid)[:, None], x_post - x_prev, np.nan)
        self._remember(index[measured.valid], frame, x_post[measured.valid])
        if s.lk_fallback:  # found with a vouched reference: where the re-acquisition's first patch is looked for
            found_vouched = measured.valid & self.vouched[index]
            self.vouched_seen[index[found_vouched]] = x_post[found_vouched]
            self.found_run[index] = np.where(measured.valid, self.found_run[index] + 1, 0)
            steady = found_vouched & (self.found_run[index] >= STEADY_FRAMES)
            self.steady_seen[index[steady]] = x_post[steady]
        retaken = np.zeros(len(index), bool)
        self.anchor_held[index[~measured.valid]] = False
        self.offset_floor[index] = 0.0
        if not s.reference_update:
            return retaken
        candidates = np.flatnonzero(measured.valid & found_before
                                    & (measured.residual > s.update_residual * self._noise_ssd()))
        if not candidates.size:
            return retaken
        at, anchored = self._anchored(index[candidates], frame, x_post[candidates])
        patches = self.measure.templates(frame.gray, at)
        before = self.measure.templates(prev.gray, x_prev[candidates])
        steady = self.measure.cost(patches, before) <= s.update_abruptness * measured.residual[candidates]
        self._take(index[candidates[steady]], patches[steady], self._wide_patches(frame, at[steady]))
        retaken[candidates[steady]] = True
        self.vouched[index[candidates[steady]]] = anchored[steady] | (s.drift_check is None)
        if s.drift_check is not None:
            radius = np.where(anchored, np.linalg.norm(at - x_post[candidates], axis=1), s.drift_check)
            self.offset_floor[index[candidates[steady]]] = radius[steady] ** 2 / 4
        return retaken

    def _anchored(self, index: np.ndarray, frame: Frame, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(n, 2) where points ``index`` re-take their reference, and (n,) bool whether that is their first patch's
        match: the first patch's match (``drift_anchors``, ``drift_check_template`` px) in a square of half-size
        ``drift_check`` around (n, 2) estimates ``xy`` where it is informative and lies within ``drift_check`` px of
        them, else ``xy`` (Matthews, Ishikawa & Baker 2004, "The template update problem": each re-take at the
        estimate adds its error to every later match; the first patch, where it still fits, holds the re-takes to
        the point). With ``warp_reference`` the first patch is matched warped by J since the query where the point has
        been found on every frame since (``anchor_held``; module docstring)."""
        reach = self.settings.drift_check
        if reach is None or not len(index):
            return xy, np.zeros(len(index), bool)
        anchors = self.drift_anchors[index]
        held = self.anchor_held[index]
        if self.settings.warp_reference and self.drift_anchors is self.anchors and held.any():
            # the first patch warped by J since the query where it held (module docstring); anchors is a copy
            anchors[held] = self._warped(anchors[held], self.anchor_wide[index[held]], self.anchor_warp[index[held]],
                                         frame, xy[held])
        m = self.anchor_measure.measure(frame.gray, anchors, xy,
                                        _square_gate(reach, len(index), self.gamma), self.noise_sigma)
        with np.errstate(invalid="ignore"):
            near = m.informative & (np.linalg.norm(m.z - xy, axis=1) <= reach)
        return np.where(near[:, None], m.z, xy), near
