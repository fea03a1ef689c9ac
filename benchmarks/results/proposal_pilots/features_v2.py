"""Candidate features v2 for the pilot: v1's plus the heading against the seen footprint's major axis
(cos and sin of twice the angle: a closing axis and its reverse are one), the minor extent, and the
footprint's span along the heading and across it (what the fingers close over, what they straddle)."""
import numpy as np
from scenegen.policy import proposal_model as pm

_v1 = pm.candidate_features

def candidate_features_v2(candidate, view):
    base = _v1(candidate, view)
    _, heading = pm._point_and_heading(candidate)
    t = view.target
    h = np.arctan2(heading[1], heading[0])
    d = h - t.yaw
    major, minor = t.extent
    span_along = abs(np.cos(d)) * major + abs(np.sin(d)) * minor
    span_across = abs(np.sin(d)) * major + abs(np.cos(d)) * minor
    return np.concatenate([base, np.asarray([np.cos(2 * d), np.sin(2 * d), minor, span_along, span_across], np.float32)])

FEATURES_V2 = pm.FEATURES + 5
