"""Reward program for: Robot grasping scene where all support surfaces are within a 1.0 m vertical reach limit

Written by the iARCS offline planner. Each check returns a soft satisfaction in [0, 1] (1 when it holds,
decaying smoothly with the distance to holding); the reward is their weighted mean. The UPPER_CASE
constants are the thresholds; reflection relaxes or tightens them.
"""
import math
import torch


# Thresholds and softness of the checks
HEIGHT_LIMIT = 1.0  # m: highest allowed top of a support surface
HEIGHT_SCALE = 0.2  # m: softness of the height penalty
AND_SHARE = 0.5  # soft AND: share of the product (the rest is the mean of the parts)

# Weights of the checks (relations that carry the constraint weigh more)
W_HEIGHT_SUPPORT = 2.0


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


def check_height_support(scene):
    """Every support surface has its top at most 1 m above the floor (and there is at least one)."""
    mask = scene.objects('support_surface')
    has_any = torch.clamp(mask.float().sum(dim=1), max=1.0)
    low_enough = scene.below(scene.top_height, HEIGHT_LIMIT, scale=HEIGHT_SCALE)
    # "all of them": the worst one counts, plus the average so each lowered object earns credit
    return has_any * (0.5 * scene.all_of(low_enough, mask) + 0.5 * scene.mean_of(low_enough, mask))


def reward(scene):
    """Weighted mean of the checks, in [0, 1]."""
    total = (W_HEIGHT_SUPPORT * clean(check_height_support(scene)))
    return total / (W_HEIGHT_SUPPORT)
