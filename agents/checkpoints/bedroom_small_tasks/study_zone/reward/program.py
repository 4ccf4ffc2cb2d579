"""Reward program for: A bedroom scene with a functional study zone

Written by the iARCS offline planner. Each check returns a soft satisfaction in [0, 1] (1 when it holds,
decaying smoothly with the distance to holding); the reward is their weighted mean. The UPPER_CASE
constants are the thresholds; reflection relaxes or tightens them.
"""
import math
import torch


# Thresholds and softness of the checks
FRONT_DEPTH = 0.9  # m: chair, stool or dressing chair at most this far beyond the front
FRONT_MARGIN = 0.1  # m: lateral slack beyond the half width
FRONT_SCALE = 0.15  # m: softness
AND_SHARE = 0.5  # soft AND: share of the product (the rest is the mean of the parts)

# Weights of the checks (relations that carry the constraint weigh more)
W_STUDY_SEAT_IN_FRONT_OF_DESK = 2.0
W_HAS_STUDY_SEAT = 0.5
W_HAS_DESK = 0.5


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


def check_study_seat_in_front_of_desk(scene):
    """Study zone: a chair, stool or dressing chair in front of a desk (within its width + 0.1 m laterally, up
    to 0.9 m beyond its front)."""
    refs, items = scene.objects('desk'), scene.objects('chair', 'stool', 'dressing_chair')
    offset = scene.local_offset()                       # [b, i, j]: desk i's frame
    lateral, ahead = offset[..., 0], offset[..., 1]     # + = i's left, + = in front of i
    half_w = (scene.size[..., 0] / 2).clamp(min=0.05).unsqueeze(2)
    half_d = (scene.size[..., 2] / 2).clamp(min=0.05).unsqueeze(2)
    centred = scene.below(lateral.abs() - half_w, FRONT_MARGIN, scale=FRONT_SCALE)
    not_behind = scene.below(-ahead, 0.0, scale=FRONT_SCALE)
    close = scene.below(ahead - half_d, FRONT_DEPTH, scale=FRONT_SCALE)
    return scene.best_pair(soft_and(centred, not_behind, close), refs, items)


def check_has_study_seat(scene):
    """There is at least one chair, stool or dressing chair."""
    return torch.clamp(scene.count('chair', 'stool', 'dressing_chair'), max=1.0)


def check_has_desk(scene):
    """There is at least one desk."""
    return torch.clamp(scene.count('desk'), max=1.0)


def reward(scene):
    """Weighted mean of the checks, in [0, 1]."""
    total = (W_STUDY_SEAT_IN_FRONT_OF_DESK * clean(check_study_seat_in_front_of_desk(scene))
             + W_HAS_STUDY_SEAT * clean(check_has_study_seat(scene))
             + W_HAS_DESK * clean(check_has_desk(scene)))
    return total / (W_STUDY_SEAT_IN_FRONT_OF_DESK + W_HAS_STUDY_SEAT + W_HAS_DESK)
