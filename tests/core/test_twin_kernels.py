"""The compiled twin kernels' violation codes are the codes the telemetry and the supervisor report."""

from core import twin_kernels
from core.plan.limits import LimitCode


def test_violation_codes_match_the_telemetry_limit_codes() -> None:
    for code in (
        LimitCode.ROD_REACH,
        LimitCode.STROKE,
        LimitCode.BASE_JOINT_CONE,
        LimitCode.PLATFORM_JOINT_CONE,
        LimitCode.TILT,
        LimitCode.SLIDER_VELOCITY,
        LimitCode.SLIDER_ACCELERATION,
        LimitCode.COLLISION,
    ):
        assert getattr(twin_kernels, code.name) == code.value, code.name
