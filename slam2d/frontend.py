"""placeholder until local SLAM lands"""
from slam2d.mapper import OdometryTracker as LocalSlam  # noqa: F401
