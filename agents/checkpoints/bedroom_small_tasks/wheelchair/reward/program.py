"""Reward program for: A wheelchair-accessible bedroom

Written by the iARCS offline planner. Each check returns a soft satisfaction in [0, 1] (1 when it holds,
decaying smoothly with the distance to holding); the reward is their weighted mean. The UPPER_CASE
constants are the thresholds; reflection relaxes or tightens them.
"""
import math
import torch


# Thresholds and softness of the checks
PATH_WIDTH = 0.9  # m: clear width of the paths
PATH_SCALE = 0.1  # m: softness
TURN_DIAMETER = 1.5  # m: diameter of the free circle
TURN_NEAR = 0.5  # m: largest gap between the circle and the object
TURN_SCALE = 0.1  # m: softness
AND_SHARE = 0.5  # soft AND: share of the product (the rest is the mean of the parts)
PARTIAL_CREDIT = 1  # 1: add partial-credit calls with a smaller free-space radius
PARTIAL_SHRINK = 0.7  # radius factor of those partial-credit calls

# Weights of the checks (relations that carry the constraint weigh more)
W_CLEAR_PATHS = 2.0
W_TURNING_CIRCLE = 2.0
W_HAS_BED = 0.5


def clean(x):
    """A check's value as a finite float tensor in [0, 1]."""
    return torch.nan_to_num(x.float(), nan=0.0, posinf=1.0, neginf=0.0).clamp(0.0, 1.0)


def soft_and(*parts):
    """Soft AND: the product (all parts together) blended with the mean (credit for each part)."""
    product, total = parts[0], parts[0]
    for part in parts[1:]:
        product = product * part
        total = total + part
    return AND_SHARE * product + (1.0 - AND_SHARE) * total / len(parts)


def check_clear_paths(scene):
    """Paths at least 0.9 m wide (agent radius 0.45 m) reach every ground object."""
    ground = scene.objects("ground")
    radius = PATH_WIDTH / 2
    # 1 for a reached object, less the narrower its path (a gradient that opens the path)
    reach = scene.above(scene.path_clearance(radius=radius), radius, scale=PATH_SCALE)
    # the fraction of reachable objects is the partial credit; all of them is full credit
    score = 0.5 * scene.mean_of(reach, ground) + 0.5 * scene.all_of(reach, ground)
    if PARTIAL_CREDIT:
        narrower = scene.reachable(radius=radius * PARTIAL_SHRINK).float()
        score = 0.8 * score + 0.2 * scene.mean_of(narrower, ground)
    return score


def check_turning_circle(scene):
    """A free turning circle of 1.5 m diameter within 0.5 m of a bed."""
    near = scene.objects('bed')
    radius = TURN_DIAMETER / 2
    # 1 when the circle fits, less the smaller the largest free circle there (a gradient that makes room)
    full = scene.above(scene.circle_clearance(radius, near=near, within=TURN_NEAR), radius, scale=TURN_SCALE)
    if not PARTIAL_CREDIT:
        return full
    # partial credit: a smaller circle at the same place, or the full circle anywhere
    smaller = scene.free_circle(radius * PARTIAL_SHRINK, near=near, within=TURN_NEAR).float()
    anywhere = scene.free_circle(radius).float()
    return 0.6 * full + 0.2 * smaller + 0.2 * anywhere


def check_has_bed(scene):
    """There is at least one bed."""
    return torch.clamp(scene.count('bed'), max=1.0)


def reward(scene):
    """Weighted mean of the checks, in [0, 1]."""
    total = (W_CLEAR_PATHS * clean(check_clear_paths(scene))
             + W_TURNING_CIRCLE * clean(check_turning_circle(scene))
             + W_HAS_BED * clean(check_has_bed(scene)))
    return total / (W_CLEAR_PATHS + W_TURNING_CIRCLE + W_HAS_BED)
