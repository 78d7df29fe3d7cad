"""Typed settings of the UWB layer: initialisation, refinement and localisation updates (the `[uwb]` config section)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from uwbcal.pipeline.core.names import INIT_METHODS, REFINE_METHODS

ANTENNA_PATTERN_SIGMA = 0.05  # [m] a UWB antenna's direction-dependent range bias (per component)


class UwbConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    init_method: Literal[("auto", *INIT_METHODS)] = Field(
        "auto",
        description="auto: ri-robust on real recordings (NLOS is the rule there), ri (the paper's) on simulated",
    )
    refine_method: Literal[(*REFINE_METHODS, "none")] = Field(
        "skf", description="refinement (paper stage 2): skf = Schmidt (pose not updated), ekf = joint, none"
    )
    sigma_range: float | None = Field(
        None, gt=0, description="range noise sigma [m]; default calibration or 0.1"
    )
    sigma_scale: float = Field(
        1.0, gt=0, description="assumed / nominal noise ratio (sigma_U of paper Table 1)"
    )
    chi2_quantile: float | None = Field(
        0.95, gt=0, lt=1, description="NIS gate of range updates (update_loss gate); None: off"
    )
    update_loss: Literal["auto", "gate", "huber", "cauchy"] = Field(
        "auto",
        description="range updates: gate (reject NIS > chi2_quantile), or a robust loss on the innovation (R "
        "inflated by the IRLS weight, scale robust_scale, no hard gate); auto: cauchy with ri-robust, else gate",
    )
    gate_window_s: float = Field(
        20.0,
        gt=0,
        description="sliding window of the range gate warning: per anchor, its ranges of this many seconds at its "
        "mean range rate in the stage (NLOS bursts of real data last up to ~10 s; a walking anchor or a diverging "
        "pose stays)",
    )
    gate_min_ranges: int = Field(20, ge=2, description="ranges a gate warning window needs at least")
    gate_max_rejected: float = Field(
        0.6,
        gt=0,
        le=1,
        description="refine / localize warn when more than this fraction of an anchor's ranges in a gate_window_s "
        "window fail the chi2_quantile gate (rejected, or with a robust loss beyond it; consistent: "
        "1 - chi2_quantile): its estimate, its ranges (NLOS) or the pose disagree there",
    )
    robust_loss: Literal["huber", "cauchy"] = Field(
        "cauchy", description="loss of ri-robust and of the search"
    )
    robust_scale: float = Field(0.5, gt=0, description="robust loss scale [m] at the nominal sigma")
    force: bool = Field(False, description="initialise even on a degenerate (rank-deficient) geometry")
    beta_sigma: float | None = Field(
        None, gt=0, description="prior sigma of beta; default calibration uwb.beta_prior.sigma, else 0.05"
    )
    estimate_beta: bool = Field(
        True,
        description="estimate beta at init under its prior (else fixed to the prior mean, 1 without a prior)",
    )
    min_ranges: int = Field(20, ge=5, description="fewer ranges in the init window: anchor skipped")
    n_perturbed_starts: int = Field(
        4, ge=0, description="extra starts of the initialiser around the closed form (multi-start)"
    )
    gamma_prior_mean: float | None = Field(
        None, description="override uwb.gamma_prior.mean of the calibration"
    )
    offset_sigma_m: float = Field(
        0.3,
        gt=0,
        description="prior sigma of a range offset [m] when the calibration states no gamma prior (what UWB "
        "hardware has: decimetres); an offset enters an anchor's model only when held-out ranges demand it",
    )
    antenna_pattern_sigma_m: float | None = Field(
        None,
        ge=0,
        description="evidence range model: size [m] of a UWB antenna's direction-dependent range bias (per "
        "component of a bias linear in the direction of arrival); it mimics a displaced anchor, so the anchor's "
        "covariance carries its effect; default the calibration's uwb.antenna_pattern_sigma, else 0.05 (0: left "
        "out)",
    )

    def pattern_sigma(self, calibration: Mapping | None = None) -> float:
        """The antenna pattern's size: config, else calibration uwb.antenna_pattern_sigma, else 0.05 m."""
        if self.antenna_pattern_sigma_m is not None:
            return float(self.antenna_pattern_sigma_m)
        stated = ((calibration or {}).get("uwb") or {}).get("antenna_pattern_sigma")
        return float(ANTENNA_PATTERN_SIGMA if stated is None else stated)

    gamma_prior_sigma: float | None = Field(None, gt=0, description="override uwb.gamma_prior.sigma")
    pose_sigma_floor_m: float = Field(0.0, ge=0, description="added to the pose position sigma at init")
    residual_factor: float = Field(
        3.0, gt=1, description="post-fit residual spread > factor x sigma: warning"
    )
    init_probe_period_s: float | None = Field(
        2.0,
        gt=0,
        description="MSCKF: keep the pose every this many seconds of the init window as a considered (Schmidt) "
        "variable, so that the anchors' cross-covariances with the filter are exact (the paper's window states "
        "X_I; 1, 2 and 5 s give the same anchor NEES); None: random-walk approximation from the poses' marginal "
        "covariances",
    )
    clock_scan_s: float = Field(
        0.5,
        ge=0,
        description="evidence range model: the range-to-pose clock offset is scanned over +-this [s] and used "
        "when its evidence demands it (the ranges re-stamped by it in every later stage); 0: off",
    )
    search: bool = Field(
        True,
        description="the evidence fit as the initialiser: a robust position fit; an offset, a scale or per-link "
        "offsets enter only when their log evidence (the ranges' likelihood deflated for correlated errors) beats "
        "the simpler model's by a Bayes factor of 3; the covariance carries what the model leaves out (the other "
        "basin, a left-out offset, errors correlated along the path, an antenna pattern); not determined when the "
        "horizontal sigma exceeds max_sigma_horizontal_m in any direction. false: the paper's multi-start (closed "
        "form, its mirror, perturbed starts), for the paper's experiments",
    )
    lever_arms: Literal["auto", "given", "planar"] = Field(
        "auto",
        description="antenna lever arms: given (the calibration's, rotated by the full attitude) or planar (a "
        "planar carrier: the in-plane arms estimated from the ranges jointly with anchors and link offsets, "
        "turned by the heading about the plane normal; planar_levers); auto: planar when the pose source's "
        "carrier moves in a plane and turns",
    )
    anchor_z_prior: dict[str, float] | dict[str, dict[str, float]] | None = Field(
        None,
        description="prior on anchor heights: {mean, sigma} for all anchors, or {anchor id: {mean, sigma}}",
    )
    max_init_ranges: int = Field(
        2000, ge=50, description="dense ranging: the init window of an anchor is evenly subsampled to this"
    )
    max_sigma_horizontal_m: float = Field(
        1.0,
        gt=0,
        description="an anchor whose horizontal sigma after the search (or after refinement: the sigma the run "
        "reports) exceeds this is not (yet) determined",
    )
    join_sigma_m: float = Field(
        0.3,
        gt=0,
        description="per-anchor schedule: an anchor joins the refinement at the first prefix of its ranges whose "
        "horizontal sigma is below this and below join_ratio x its median range (a start good enough for the "
        "filter's first-estimate Jacobians); one that never gets there but is determined by all its ranges is "
        "initialised from all of them",
    )
    join_ratio: float = Field(0.02, gt=0, description="see join_sigma_m (about 1 degree of bearing)")
    min_duration_s: float = Field(
        5.0, ge=0, description="an anchor ranged over a shorter time span is not determined"
    )
    correlation_block_s: float | None = Field(
        10.0,
        gt=0,
        description="block length [s] of the check for time-correlated range errors at init (batch means); "
        "its variance factor kappa scales the anchor covariance and the range noise of refine/localize. "
        "None: off (kappa = 1)",
    )

    def sigma(self, calibration: Mapping | None = None) -> float:
        """The nominal range sigma: config, else calibration uwb.sigma_range, else 0.1 m."""
        if self.sigma_range is not None:
            return float(self.sigma_range)
        uwb = (calibration or {}).get("uwb", {}) or {}
        return float(uwb.get("sigma_range") or 0.1)

    def beta_prior(self, calibration: Mapping | None = None) -> tuple[float, float]:
        """(mean, sigma) of beta: config beta_sigma, else calibration uwb.beta_prior, else (1, 0.05)."""
        uwb = (calibration or {}).get("uwb", {}) or {}
        bp = uwb.get("beta_prior") or {}
        mean = float(bp.get("mean", 1.0))
        sigma = self.beta_sigma if self.beta_sigma is not None else bp.get("sigma")
        return mean, float(sigma if sigma else 0.05)

    def init_beta_prior(self, calibration: Mapping | None = None) -> tuple[float, float] | None:
        """The beta prior the initialiser estimates beta under, or None (beta fixed to 1)."""
        return self.beta_prior(calibration) if self.estimate_beta else None

    def z_prior(self, anchor: Any) -> tuple[float, float] | None:
        """(mean, sigma) of the anchor's height from ``anchor_z_prior``, or None."""
        zp = self.anchor_z_prior
        if not zp:
            return None
        if "mean" in zp:
            return float(zp["mean"]), float(zp.get("sigma", 1.0))  # type: ignore[arg-type]
        one = zp.get(str(anchor))
        if isinstance(one, dict) and "mean" in one:
            return float(one["mean"]), float(one.get("sigma", 1.0))
        return None

    def offset_prior(self, calibration: Mapping | None = None) -> tuple[float, float]:
        """(mean, sigma) of a range offset for the evidence rule: the calibration's gamma prior, else
        N(0, offset_sigma_m^2)."""
        return self.gamma_prior(calibration) or (0.0, float(self.offset_sigma_m))

    def gamma_prior(self, calibration: Mapping | None = None) -> tuple[float, float] | None:
        uwb = (calibration or {}).get("uwb", {}) or {}
        gp = uwb.get("gamma_prior") or {}
        mean = self.gamma_prior_mean if self.gamma_prior_mean is not None else gp.get("mean")
        sigma = self.gamma_prior_sigma if self.gamma_prior_sigma is not None else gp.get("sigma")
        if mean is None:
            return None
        return float(mean), float(sigma if sigma else 1.0)
