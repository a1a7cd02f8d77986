"""The built-in filters' settings models, apart from the filters: the config validates the settings of every
registered filter, and a run imports only the filter it uses (``registry.py``)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from condtrack_cli.settings import OPENCV_INT_MAX, StageSettings

#: With ``lk_fallback``: frames after its last match during which a lost point is searched for around where it was
#: last found (``reference.py``, ``ReferenceMatcher._reacquire``)
REACQUIRE_FRAMES = 15

#: Frames in a row a point must have been found on for where it is found with a vouched reference to be its
#: ``steady_seen``, the centre of the re-acquisition's last first-patch search (``reference.py``, ``_reacquire``).
STEADY_FRAMES = 5


class InitialStateSettings(StageSettings):
    """Settings of every filter that carries a covariance from the query on (MDR, CLF, CNLF)."""

    initial_std: float = Field(0.5, gt=0, le=1000, description="std of the position at the query frame (px)")


class MeasuredFilterSettings(InitialStateSettings):
    """Settings shared by the filters that measure a reference patch (CLF, CNLF)."""

    odd_fields = ("drift_check_template",)
    nominal_r: float = Field(1.0, gt=0, description="variance sizing the search before a point has a finite R_k (px^2)")
    gate_r_min: float = Field(0.1, gt=0, description="least variance of the R sizing the search (px^2)")
    gate_r_max: float = Field(25.0, gt=0, description="largest variance of the R sizing the search (px^2)")
    reference_update: bool = Field(True, description="refresh a point's reference patch when it no longer matches well")
    update_residual: float = Field(
        4.0, gt=1, description="refresh when the match residual exceeds this many times its noise-only expectation"
    )
    drift_check: float | None = Field(
        3.0, gt=0,
        description="a refresh re-takes the patch where the point's first reference matches, when that match lies "
                    "within this many px of the estimate (drift correction; null: at the estimate, the paper's)",
    )
    drift_check_template: int | None = Field(
        None, ge=3, le=63,
        description="side of the first patch the drift check matches (px, odd; null: measure.template, the "
                    "reference's); wider, what changes inside the point's own patch (a mouth, a blink) moves its "
                    "match less, but a thin limb's wider patch holds the ground behind it",
    )
    warp_reference: bool = Field(
        True,
        description="match the reference patch warped by the local field's deformation since it was taken, where "
                    "that moves some patch pixel by half a pixel or more, within the patch's margin, and fits the "
                    "frame at the prediction clearly better than the patch as taken; the drift check's first patch "
                    "likewise, by the deformation since the query, while the point has been found on every frame "
                    "since (false: as taken, the paper's)",
    )
    update_abruptness: float = Field(
        0.8, gt=0, le=1, description="no refresh when more than this share of the residual appeared since the last frame"
    )
    foreign_residual: float | None = Field(
        12.0, gt=1,
        description="a match whose residual exceeds this many times the point's usual one lies on what covers it: "
                    "not used (null: off)",
    )
    lk_fallback: bool = Field(
        True,
        description="a point found on the previous frame whose match is not used is matched again around where "
                    "pyramidal Lucas-Kanade moves it, where its last measured step carries it, then where a coarse "
                    "search at half resolution finds its patch, with the same tests; a point lost for 1 to "
                    f"{REACQUIRE_FRAMES} frames is searched for around where it was last found, by its last patch then "
                    "by its first, and by its first around where it was last found with a reference that patch vouched for "
                    f"and where it was last so found after {STEADY_FRAMES} found frames in a row "
                    "(false: the gate around the prediction only, the paper's)",
    )
    lk_better: float = Field(
        0.5, gt=0,
        description="lk_fallback: a match around a fallback centre is used only where its residual is below "
                    "this share of the best residual in the gate around the prediction",
    )
    flat_visible_residual: float | None = Field(
        2.5, gt=1,
        description="a point whose correlation surface is too flat to measure (R = inf) is still reported visible "
                    "when its best match, or its patch at the prediction, fits its reference within this many times "
                    "its usual residual; the measurement is not used either way (null: reported not visible, the "
                    "paper's)",
    )


class STKSettings(StageSettings):
    frame_windows = ("win_size",)
    covariance = False
    stage_kinds = ()
    win_size: int = Field(21, ge=3, description="side of the Lucas-Kanade window (px)")
    levels: int = Field(4, ge=1, le=8, description="pyramid levels (OpenCV maxLevel = levels - 1; 4: OpenCV maxLevel 3)")
    max_iterations: int = Field(30, ge=1, le=OPENCV_INT_MAX, description="iterations per level")
    epsilon: float = Field(0.01, gt=0, description="stop when an iteration moves the point less than this (px)")
    fb_threshold: float = Field(1.0, gt=0, description="forward-backward distance above which a point is not visible (px)")
    min_eig_threshold: float = Field(1e-4, ge=0, description="OpenCV minEigThreshold: LK fails below this")


class CLFSettings(MeasuredFilterSettings):
    """The CLF's settings: those of every filter that measures a reference patch, and its dynamics."""

    smoother = "rts"
    dynamics: Literal["select", "local", "global"] = Field(
        "select",
        description="motion predicting the gate: global (paper's CLF), local (window around the point) or select (per point)",
    )
    select_margin: float = Field(
        0.5, ge=0, description="select: the local motion predicts a point while it misses the measurement by this much less (px)"
    )
    select_frames: int = Field(
        2, ge=1, description="select: consecutive found frames the local motion must win before a point switches to it"
    )


class MDRSettings(InitialStateSettings):
    """MDR's settings: the initial position std and which motion moves the points (no measurement stage)."""

    stage_kinds = ("motion",)

    dynamics: Literal["global", "local"] = Field(
        "global",
        description="motion moving the points: global (the dominant fit) or local (the window around each point, the CNLF's; paper §6: MDR is the filter's own dynamics)",
    )


class CNLFSettings(MeasuredFilterSettings):
    smoother = "ffbsm"
    extras = ("particles",)
    particles: int = Field(100, ge=1, le=10000, description="particles per point (the paper's N = 100)")
    ess_fraction: float = Field(0.5, gt=0, le=1, description="resample when the effective sample size falls below this x N")
    resampling: Literal["systematic", "residual"] = Field("systematic", description="resampling scheme")
    layer_jump: float | None = Field(
        None, gt=0,
        description="a point not found, whose local motion departs from its own layer's by more than this many px "
                    "(and that motion's size), is moved by its layer's motion, not by what now covers it "
                    "(null, the default: always the local motion, the paper's; docs/departures.md)",
    )
    path_lag: int | None = Field(
        10, ge=0,
        description="frames of particle paths kept: a frame's path estimate uses the weights this many frames later "
                    "(or the clip's end); null keeps them all (the paper's estimate; memory grows with the clip)",
    )
    path_points: Literal["proposal_means", "particles"] = Field(
        "proposal_means",
        description="what a frame's path estimate averages: each particle's proposal mean (the mean it was drawn "
                    "around, eq. 11: the draw's own noise left out) or the particles themselves (the paper's Fig. 2)",
    )


class AutoSettings(StageSettings):
    filter_sections = ("clf", "cnlf")
    smoother = "rts+ffbsm"
    extras = ("particles", "segmentation")
    integration_frames: int = Field(3, ge=1, description="frames over which a point's evidence is averaged")
    evidence_margin: float = Field(
        0.5, ge=0, description="change filter when the averaged evidence passes +- this (half squared Mahalanobis units)"
    )
    lost_evidence: float = Field(
        0.25, ge=0,
        description="a point not found keeps the local motion while the mean evidence of its measurements is above this",
    )
    keep_local_clf: bool = Field(
        True,
        description="a point on the CLF that the CLF predicts by the local motion stays there whatever its evidence "
                    "(rule 4 still routes a point not found; false: the evidence hands it back to the CNLF)",
    )
    occluder_jump: float | None = Field(
        1.5, gt=0,
        description="rule 5: a point found whose local step departs from its last measured step by more than this "
                    "many px (and that step's size), while the dominant step does not, is moved by the dominant motion "
                    "and reported not visible (null: off)",
    )
