"""Metric profiles: the rules that turn one trajectory into NE / SR / OSR / SPL / nDTW (docs/METRICS.md).

Two named profiles are always reported: `openfly` (parity with the official `train/eval.py`) and
`standard` (habitat / VLN-CE style: STOP needed, collisions fail, clamped SPL on the reference path).
"""

from __future__ import annotations

from dataclasses import dataclass

from openfly_agent import constants as C

COMPARISONS = ("<", "<=")
SPL_REFERENCES = ("straight_line", "reference_path")
COLLISION_POLICIES = ("ignore", "end_fail", "count")


@dataclass(frozen=True)
class MetricProfile:
    """How one benchmark scores a trajectory.

    Attributes:
        name: registry key, e.g. "openfly".
        success_radius: metres; success when the distance to the goal compares true against it.
        distance_dims: 3 (x, y, z) or 2 (x, y only, AerialVLN style) for every distance to the goal
            (NE, SR, OSR, nDTW). Path lengths are always 3-D.
        comparison: "<" (OpenFly, habitat) or "<=" (AerialVLN, TravelUAV).
        stop_required: success needs the agent's STOP (habitat); otherwise wherever it ends counts.
        spl_reference: "straight_line" (start -> goal, OpenFly) or "reference_path" (ground-truth
            polyline length, our stand-in for the geodesic shortest path).
        spl_clamp: SPL = S * L / max(P, L) when True, S * L / P when False (can exceed 1).
        spl_path_epsilon: metres added to the executed length P (the official code starts at 1e-3).
        collision_policy: "ignore" (no effect), "end_fail" (the episode ends before the colliding
            move and fails) or "count" (the episode goes on; collisions are only counted).
        max_steps: actions evaluated at most (STOP included); later ones are cut off.
        osr_includes_start: whether the start pose can make oracle success.
    """

    name: str
    success_radius: float = C.SUCCESS_RADIUS_M
    distance_dims: int = 3
    comparison: str = "<"
    stop_required: bool = False
    spl_reference: str = "straight_line"
    spl_clamp: bool = False
    spl_path_epsilon: float = 0.0
    collision_policy: str = "ignore"
    max_steps: int = C.MAX_EPISODE_STEPS
    osr_includes_start: bool = False

    def __post_init__(self) -> None:
        if not self.name:
            raise ValueError("MetricProfile.name must be a non-empty string")
        if not self.success_radius > 0:
            raise ValueError(
                f"profile {self.name}: success_radius must be > 0 metres, got {self.success_radius}"
            )
        if self.distance_dims not in (2, 3):
            raise ValueError(f"profile {self.name}: distance_dims must be 2 or 3, got {self.distance_dims}")
        if self.comparison not in COMPARISONS:
            raise ValueError(
                f"profile {self.name}: comparison must be one of {COMPARISONS}, got {self.comparison!r}"
            )
        if self.spl_reference not in SPL_REFERENCES:
            raise ValueError(
                f"profile {self.name}: spl_reference must be one of {SPL_REFERENCES}, "
                f"got {self.spl_reference!r}"
            )
        if self.spl_path_epsilon < 0:
            raise ValueError(
                f"profile {self.name}: spl_path_epsilon must be >= 0, got {self.spl_path_epsilon}"
            )
        if self.collision_policy not in COLLISION_POLICIES:
            raise ValueError(
                f"profile {self.name}: collision_policy must be one of {COLLISION_POLICIES}, "
                f"got {self.collision_policy!r}"
            )
        if self.max_steps < 1:
            raise ValueError(f"profile {self.name}: max_steps must be >= 1, got {self.max_steps}")

    def within(self, distance: float) -> bool:
        """Whether `distance` (metres) counts as reaching the goal under this profile."""
        if self.comparison == "<":
            return distance < self.success_radius
        return distance <= self.success_radius


# Parity with SHAILAB-IPEC/OpenFly-Platform train/eval.py (docs/OFFICIAL_OPENFLY.md section 6.2).
OPENFLY = MetricProfile(
    name="openfly",
    success_radius=C.SUCCESS_RADIUS_M,
    distance_dims=3,
    comparison="<",
    stop_required=False,
    spl_reference="straight_line",
    spl_clamp=False,
    spl_path_epsilon=1e-3,
    collision_policy="ignore",
    max_steps=C.MAX_EPISODE_STEPS,
    osr_includes_start=False,
)

# Habitat / VLN-CE rules (Anderson et al. 2018) at the OpenFly radius and step budget.
STANDARD = MetricProfile(
    name="standard",
    success_radius=C.SUCCESS_RADIUS_M,
    distance_dims=3,
    comparison="<",
    stop_required=True,
    spl_reference="reference_path",
    spl_clamp=True,
    spl_path_epsilon=0.0,
    collision_policy="end_fail",
    max_steps=C.MAX_EPISODE_STEPS,
    osr_includes_start=True,
)

PROFILES: dict[str, MetricProfile] = {OPENFLY.name: OPENFLY, STANDARD.name: STANDARD}
DEFAULT_PROFILE_NAMES = (OPENFLY.name, STANDARD.name)


def get_profile(name: str | MetricProfile) -> MetricProfile:
    """The registered profile called `name` (a `MetricProfile` is returned as is)."""
    if isinstance(name, MetricProfile):
        return name
    try:
        return PROFILES[name]
    except KeyError:
        raise KeyError(f"unknown metric profile {name!r}; registered profiles: {sorted(PROFILES)}") from None
