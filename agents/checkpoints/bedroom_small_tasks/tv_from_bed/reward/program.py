"""Reward program for: Room with a TV stand positioned so a farsighted person can view a 4K TV from bed

Written by the iARCS offline planner. Each check returns a soft satisfaction in [0, 1] (1 when it holds,
decaying smoothly with the distance to holding); the reward is their weighted mean. The UPPER_CASE
constants are the thresholds; reflection relaxes or tightens them.
"""
import math
import torch


# Thresholds and softness of the checks
VIEW_MIN = 2.0  # m: closest viewing distance
VIEW_MAX = 4.0  # m: farthest viewing distance
VIEW_ANGLE_DEG = 30.0  # degrees: largest viewing / facing angle
VIEW_DISTANCE_SCALE = 0.4  # m: softness of the distance range
VIEW_ANGLE_SCALE = 0.35  # rad: softness of the angles
AND_SHARE = 0.5  # soft AND: share of the product (the rest is the mean of the parts)

# Weights of the checks (relations that carry the constraint weigh more)
W_TV_VIEWED_FROM_BED = 2.0
W_HAS_TV = 0.5
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


def check_tv_viewed_from_bed(scene):
    """A bed and a TV stand 2-4 m apart, the TV stand within 30 degrees of the bed's facing direction and
    facing it within 30 degrees."""
    viewers, targets = scene.objects('bed'), scene.objects('tv_stand')
    angle = scene.facing_angle()                        # [b, i, j]: i's facing vs the direction i -> j
    limit = math.radians(VIEW_ANGLE_DEG)
    in_range = scene.within(scene.distance(), VIEW_MIN, VIEW_MAX, scale=VIEW_DISTANCE_SCALE)
    # the TV stand ahead of the bed, and turned towards it
    in_sight = scene.below(angle, limit, scale=VIEW_ANGLE_SCALE)
    turned = scene.below(angle.transpose(1, 2), limit, scale=VIEW_ANGLE_SCALE)
    return scene.best_pair(soft_and(in_range, in_sight, turned), viewers, targets)


def check_has_tv(scene):
    """There is at least one TV stand."""
    return torch.clamp(scene.count('tv_stand'), max=1.0)


def check_has_bed(scene):
    """There is at least one bed."""
    return torch.clamp(scene.count('bed'), max=1.0)


def reward(scene):
    """Weighted mean of the checks, in [0, 1]."""
    total = (W_TV_VIEWED_FROM_BED * clean(check_tv_viewed_from_bed(scene))
             + W_HAS_TV * clean(check_has_tv(scene))
             + W_HAS_BED * clean(check_has_bed(scene)))
    return total / (W_TV_VIEWED_FROM_BED + W_HAS_TV + W_HAS_BED)
