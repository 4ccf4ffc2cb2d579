"""Reward program for: A bedroom with 2 night tables on either side of the bed

Written by the iARCS offline planner. Each check returns a soft satisfaction in [0, 1] (1 when it holds,
decaying smoothly with the distance to holding); the reward is their weighted mean. The UPPER_CASE
constants are the thresholds; reflection relaxes or tightens them.
"""
import math
import torch


# Thresholds and softness of the checks
NIGHTSTAND_MIN = 2.0  # fewest nightstands wanted
COUNT_SCALE = 1.0  # one object off keeps exp(-1) of the credit
SIDE_GAP = 0.5  # m: nightstand centre at most this far out from the bed's side
SIDE_SCALE = 0.15  # softness (m, and fractions of the half depth)
AND_SHARE = 0.5  # soft AND: share of the product (the rest is the mean of the parts)

# Weights of the checks (relations that carry the constraint weigh more)
W_COUNT_NIGHTSTAND = 1.0
W_NIGHTSTAND_EITHER_SIDE_OF_BED = 2.0
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


def check_count_nightstand(scene):
    """At least 2 nightstand(s)."""
    n = scene.count('nightstand')
    return scene.above(n, NIGHTSTAND_MIN, scale=COUNT_SCALE)


def check_nightstand_either_side_of_bed(scene):
    """For the best bed: a nightstand on its left and one on its right, each along the head half with its
    centre 0 to 0.5 m out from the side."""
    refs, items = scene.objects('bed'), scene.objects('nightstand')
    pairs = scene.pair_mask(refs, items)                # [b, i, j]: bed i, nightstand j
    offset = scene.local_offset()                       # [b, i, j]: bed i's frame
    lateral, ahead = offset[..., 0], offset[..., 1]     # + = i's left, + = in front of i
    half_w = (scene.size[..., 0] / 2).clamp(min=0.05).unsqueeze(2)
    half_d = (scene.size[..., 2] / 2).clamp(min=0.05).unsqueeze(2)
    # along the head half (between the headboard and the centre), 0 to SIDE_GAP out from the side
    head_half = scene.within(ahead / half_d, -1.0, 0.0, scale=SIDE_SCALE)
    out_from_side = scene.within(lateral.abs() - half_w, 0.0, SIDE_GAP, scale=SIDE_SCALE)
    ok = soft_and(head_half, out_from_side)
    left = (ok * (lateral > 0)).masked_fill(~pairs, 0.0).amax(dim=2)
    right = (ok * (lateral < 0)).masked_fill(~pairs, 0.0).amax(dim=2)
    # full credit for both sides, a quarter for each side alone
    per_ref = 0.5 * left * right + 0.25 * (left + right)
    return per_ref.masked_fill(~refs, 0.0).amax(dim=1)


def check_has_bed(scene):
    """There is at least one bed."""
    return torch.clamp(scene.count('bed'), max=1.0)


def reward(scene):
    """Weighted mean of the checks, in [0, 1]."""
    total = (W_COUNT_NIGHTSTAND * clean(check_count_nightstand(scene))
             + W_NIGHTSTAND_EITHER_SIDE_OF_BED * clean(check_nightstand_either_side_of_bed(scene))
             + W_HAS_BED * clean(check_has_bed(scene)))
    return total / (W_COUNT_NIGHTSTAND + W_NIGHTSTAND_EITHER_SIDE_OF_BED + W_HAS_BED)
