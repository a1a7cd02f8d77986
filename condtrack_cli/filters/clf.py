"""CLF: the conditional linear filter (paper §3, §5, Fig. 1), and MDR, its dynamics alone.

Per frame, for all started points at once:
- model: the global robust motion between frames k-1 and k gives A_k, b_k of
  eq. (1) (A_k the Jacobian of x + U(x), b_k = x + U(x) - A_k x, exact for the
  affine model and a linearisation for the quadratic one) and Q_k (§5.1);
- prediction: x_{k|k-1} = A_k x + b_k, Sigma_{k|k-1} = A_k Sigma A_k^T + Q_k;
- measurement: SSD match of the reference patch in the validation gate (§5.2),
  R_k from the correlation surface (eqs. 8-10);
- update where R_k is finite and z_k is in the gate nu^T (Sigma + R_k)^-1 nu <= gamma;
  elsewhere the point coasts on the dynamics and is reported not visible.

The search region must be sized before R_k is known (DESIGN.md §3): it uses
S = Sigma_{k|k-1} + R_gate, R_gate being the point's last finite R_k (the
configured nominal one before the first), clamped to [gate_r_min, gate_r_max].
"""

from __future__ import annotations

import numpy as np
from pydantic import Field

from condtrack_cli import registry
from condtrack_cli.config import Config, StageSettings
from condtrack_cli.filters import kalman
from condtrack_cli.filters.base import Tracker
from condtrack_cli.motion.robust import displacement, jacobian, state_noise
from condtrack_cli.registry import register
from condtrack_cli.types import Frame, Queries, SequenceInfo


def build_stage(config: Config, kind: str):
    """The configured stage object of ``kind`` (e.g. the motion estimator)."""
    stage = config.stage(kind)
    return registry.get(kind, stage.name).factory(stage.settings)


def linear_dynamics(fit, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A_k (n, 2, 2) and b_k (n, 2) of eq. (1) at positions xy (n, 2): x + U(x) = A_k x + b_k near xy."""
    A = jacobian(fit, xy)
    b = xy + displacement(fit, xy) - np.einsum("nij,nj->ni", A, xy)
    return A, b


class CLFSettings(StageSettings):
    initial_std: float = Field(0.5, gt=0, description="std of the position at the query frame (px)")
    nominal_r: float = Field(1.0, gt=0, description="variance sizing the search before a point has a finite R_k (px^2)")
    gate_r_min: float = Field(0.1, gt=0, description="least variance of the R sizing the search (px^2)")
    gate_r_max: float = Field(25.0, gt=0, description="largest variance of the R sizing the search (px^2)")
    reference_update: bool = Field(True, description="refresh a point's reference patch when it no longer matches well")
    update_residual: float = Field(
        4.0, gt=1, description="refresh when the match residual exceeds this many times its noise-only expectation"
    )


class MDRSettings(StageSettings):
    initial_std: float = Field(0.5, gt=0, description="std of the position at the query frame (px)")


class MDRTracker(Tracker):
    """MDR: points moved by the dominant (global robust) motion alone, no measurement.

    The covariance is the dynamics' own, A Sigma A^T + Q accumulated; a point is
    visible while it is inside the frame (MDR has no occlusion evidence).
    """

    method = "mdr"

    def __init__(self, settings: MDRSettings, queries: Queries, info: SequenceInfo, config: Config):
        super().__init__(queries, info)
        self.settings = settings
        self.motion = build_stage(config, "motion")
        self.motion_settings = config.stage("motion").settings

    def _start(self, index: np.ndarray, frame: Frame) -> None:
        self.cov[index] = self.settings.initial_std**2 * np.eye(2)

    def _predict(self, index: np.ndarray, prev: Frame, frame: Frame) -> tuple[np.ndarray, np.ndarray]:
        fit = self.motion.fit(prev, frame)
        x = self.xy[index]
        A, b = linear_dynamics(fit, x)
        m = self.motion_settings
        return kalman.predict(x, self.cov[index], A, b, state_noise(fit, x, m.q_floor, m.q_misfit, m.misfit_window))

    def _advance(self, index: np.ndarray, prev: Frame, frame: Frame) -> None:
        self.xy[index], self.cov[index] = self._predict(index, prev, frame)
        x = self.xy[index]
        w, h = self.info.width, self.info.height
        self.visible[index] = (x[:, 0] >= -0.5) & (x[:, 0] <= w - 0.5) & (x[:, 1] >= -0.5) & (x[:, 1] <= h - 0.5)


class CLFTracker(MDRTracker):
    """CLF: MDR's prediction corrected by the SSD measurement with R_k from the surface."""

    method = "clf"

    def __init__(self, settings: CLFSettings, queries: Queries, info: SequenceInfo, config: Config):
        super().__init__(settings, queries, info, config)
        self.measure = build_stage(config, "measure")
        p, t = len(queries), self.measure.settings.template
        self.templates = np.zeros((p, t, t), np.float32)
        self.gate_r = np.repeat(settings.nominal_r * np.eye(2)[None], p, axis=0)
        self.noise_sigma: float | None = None

    def _start(self, index: np.ndarray, frame: Frame) -> None:
        super()._start(index, frame)
        if self.noise_sigma is None:
            self.noise_sigma = self.measure.noise_sigma(frame.gray)
        self.templates[index] = self.measure.templates(frame.gray, self.xy[index])

    def _advance(self, index: np.ndarray, prev: Frame, frame: Frame) -> None:
        self.visible_before = self.visible.copy()
        x_prev = self.xy[index].copy()
        x_pred, sigma_pred = self._predict(index, prev, frame)
        m = self.measure.measure(frame.gray, self.templates[index], x_pred, sigma_pred + self.gate_r[index], self.noise_sigma)
        finite_r = np.where(m.informative[:, None, None], m.R, np.eye(2))
        nu = np.where(m.informative[:, None], m.z - x_pred, 0.0)
        in_gate = kalman.mahalanobis2(nu, sigma_pred + finite_r) <= self.measure.settings.gamma
        valid = m.informative & in_gate
        self.xy[index], self.cov[index] = kalman.update(x_pred, sigma_pred, m.z, finite_r, valid)
        self.visible[index] = valid
        self.z[index], self.R[index] = m.z, m.R
        if self.settings.reference_update:
            self._refresh_references(index, prev, x_prev, frame, valid, m.residual)
        s = self.settings
        clamped = np.clip(finite_r, -s.gate_r_max, s.gate_r_max)
        clamped[:, [0, 1], [0, 1]] = np.clip(finite_r[:, [0, 1], [0, 1]], s.gate_r_min, s.gate_r_max)
        self.gate_r[index[valid]] = clamped[valid]


    def _refresh_references(
        self, index: np.ndarray, prev: Frame, x_prev: np.ndarray, frame: Frame, valid: np.ndarray, residual: np.ndarray
    ) -> None:
        """Reference update (paper §5.2): re-take the reference patch at the posterior position.

        With m template pixels and sigma the acquisition noise, m 2 sigma^2 is the
        SSD expected from noise alone. A point's reference is refreshed when
        (1) it was found this frame and the previous one (finite R_k in the gate),
        (2) its residual r_k(z_k) exceeds ``update_residual`` m 2 sigma^2: the patch
        has drifted away from the reference, and (3) the new patch matches the
        patch at the previous estimate in the previous frame within
        ``update_residual`` / 2 m 2 sigma^2: it changed slowly, as a deforming
        surface does. An occluder edge creeping over the patch changes it abruptly
        from one frame to the next and fails (3); a whole occluder fails (1).
        """
        s = self.settings
        noise_ssd = self.templates.shape[1] * self.templates.shape[2] * 2 * self.noise_sigma**2
        candidates = np.flatnonzero(valid & self.visible_before[index] & (residual > s.update_residual * noise_ssd))
        if not candidates.size:
            return
        refresh = index[candidates]
        patches = self.measure.templates(frame.gray, self.xy[refresh])
        before = self.measure.templates(prev.gray, x_prev[candidates])
        steady = ((patches - before) ** 2).sum(axis=(1, 2)) <= s.update_residual / 2 * noise_ssd
        self.templates[refresh[steady]] = patches[steady]


@register("filter", "mdr", MDRSettings, "MDR baseline: the global robust motion alone, no measurement")
def make_mdr(settings: MDRSettings, queries: Queries, info: SequenceInfo, config: Config, **_context) -> MDRTracker:
    return MDRTracker(settings, queries, info, config)


@register("filter", "clf", CLFSettings, "conditional linear filter (paper §3, Fig. 1): global motion + SSD measurement")
def make_clf(settings: CLFSettings, queries: Queries, info: SequenceInfo, config: Config, **_context) -> CLFTracker:
    return CLFTracker(settings, queries, info, config)
