"""The offline planner's checks with a scope (:mod:`rewards.planner`): relations read with their quantifier ("every
chair within 1 m of the desk" is not "a chair within 1 m of the desk") or their negation ("no chair in front of the
wardrobe"), and the checks of the broader vocabulary: distances between any two pieces of furniture, "between",
"behind", facing away, the middle of the room, centred on a wall, free space beside an object, a free square or
circle, the room's size. Each body uses :mod:`rewards.scene_api` only."""

from __future__ import annotations

from .planner_checks import PRIMARY_WEIGHT, SUPPORT_WEIGHT, Check, Entity, Param, _objects

#: Defaults when the constraint names no number (metres, degrees, square metres).
AWAY_ANGLE = 60.0          # "facing away from": the reference within 60 degrees of straight behind
BEHIND_DEPTH = 0.9         # "behind": up to 0.9 m beyond the back, within the width + 0.1 m
BEHIND_MARGIN = 0.1
BETWEEN_OFFSET = 1.0       # "between A and B": at most 1 m off the line joining their centres
WALL_AWAY = 0.5            # "away from the walls": the footprint at least 0.5 m from every wall
MIDDLE_RADIUS = 1.0        # "in the middle of the room": centre within 1 m of the room's middle
CENTRED_OFFSET = 0.3       # "centred on a wall": centre within 0.3 m of the wall's middle, along the wall
FREE_DEPTH = 0.8           # "free space in front of / beside / around": a 0.8 m strip
FREE_SHARE = 0.95          # ... of which 95 % is free
FREE_AREA = 1.5            # "an open area in the middle of the room": a free circle 1.5 m across
SMALL_ROOM = 12.0          # "a small bedroom": at most 12 m^2
LARGE_ROOM = 16.0          # "a large / spacious bedroom": at least 16 m^2

#: Quantifier readings of a relation between subjects (i) and references (j); WITHOUT: "a reference without a
#: subject in the relation" ("a desk without a chair in front of it").
SOME, EVERY, NONE, WITHOUT = "some", "every", "none", "without"


def _pair_score(kind: str) -> str:
    """Body lines setting ``ok`` [b, i, j], the soft satisfaction of "subject i <kind> reference j"."""
    if kind in ("near", "far"):
        test = "below" if kind == "near" else "above"
        return f"    ok = scene.{test}(scene.gap(), $DISTANCE, scale=$DISTANCE_SCALE)\n"
    if kind == "facing":
        return "    ok = scene.below(scene.facing_angle(), math.radians($ANGLE_DEG), scale=$ANGLE_SCALE)\n"
    if kind == "away":   # the reference behind the subject: i's forward points away from j
        return ("    ok = scene.above(scene.facing_angle(), math.pi - math.radians($ANGLE_DEG), "
                "scale=$ANGLE_SCALE)\n")
    sign = "" if kind == "in_front" else "-"
    return f"""    offset = scene.local_offset().transpose(1, 2)        # [b, i, j]: subject i in reference j's frame
    lateral, ahead = offset[..., 0], {sign}offset[..., 1]
    half_w = (scene.size[..., 0] / 2).clamp(min=0.05).unsqueeze(1)
    half_d = (scene.size[..., 2] / 2).clamp(min=0.05).unsqueeze(1)
    centred = scene.below(lateral.abs() - half_w, $MARGIN, scale=$SCALE)
    beyond = scene.below(-ahead, 0.0, scale=$SCALE)
    close = scene.below(ahead - half_d, $DEPTH, scale=$SCALE)
    ok = centred * beyond * close
"""


_WORDS = {"near": "within {d:g} m of", "far": "at least {d:g} m from", "facing": "facing (within {a:g} degrees)",
          "away": "facing away from (within {a:g} degrees of straight away)", "in_front": "in front of",
          "behind": "behind"}


def _params(kind: str, value: float) -> list[Param]:
    if kind in ("near", "far"):
        return [Param("DISTANCE", value, "m: footprint gap " + ("limit" if kind == "near" else "to keep"),
                      relax=0.3 if kind == "near" else -0.3),
                Param("DISTANCE_SCALE", 0.2, "m: softness", kind="scale")]
    if kind in ("facing", "away"):
        return [Param("ANGLE_DEG", value, "degrees: largest angle", relax=15.0),
                Param("ANGLE_SCALE", 0.35, "rad: softness", kind="scale")]
    return [Param("DEPTH", value, "m: at most this far beyond the edge", relax=0.3),
            Param("MARGIN", BEHIND_MARGIN, "m: lateral slack beyond the half width", relax=0.15),
            Param("SCALE", 0.15, "m: softness", kind="scale")]


def pair_check(kind: str, subj: Entity, ref: Entity, quant: str, value: float, phrase: str) -> Check:
    """A relation with its scope: SOME (a subject and a reference with it), EVERY (every subject with some
    reference; there is at least one subject), NONE (no subject with any reference; "far" is always NONE of
    "near") or WITHOUT (a reference with no subject in the relation). ``value``: the distance (m), angle (degrees)
    or depth (m) of ``kind``."""
    head = f"    items, refs = {_objects(subj)}, {_objects(ref)}\n    pairs = scene.pair_mask(items, refs)\n"
    score = _pair_score(kind)
    what = _WORDS[kind].format(d=value, a=value)
    if quant == SOME:
        tail = "    return scene.best_pair(ok, items, refs)\n"
        desc = f"a {subj.label} {what} a {ref.label}"
    elif quant == EVERY:
        tail = """    per_item = ok.masked_fill(~pairs, 0.0).amax(dim=2)    # each subject's best reference
    has_any = torch.clamp(items.float().sum(dim=1), max=1.0)
    # every subject: the worst one counts, plus the average so each one brought in earns credit
    return has_any * (0.5 * scene.all_of(per_item, items) + 0.5 * scene.mean_of(per_item, items))
"""
        desc = f"every {subj.label} {what} a {ref.label} (and there is at least one)"
    elif quant == WITHOUT:
        tail = """    alone = (1.0 - ok).masked_fill(~pairs, 1.0).amin(dim=1)   # [b, j]: no subject in relation to j
    return scene.any_of(alone, refs)
"""
        desc = f"a {ref.label} without any {subj.label} {what} it"
    else:
        tail = """    fine = (1.0 - ok).masked_fill(~pairs, 1.0)            # each pair keeps out of the relation
    n_pairs = pairs.float().flatten(1).sum(dim=1).clamp(min=1.0)
    mean = (fine * pairs).flatten(1).sum(dim=1) / n_pairs + (pairs.flatten(1).sum(dim=1) == 0).float()
    return 0.5 * fine.flatten(1).amin(dim=1) + 0.5 * mean.clamp(max=1.0)
"""
        desc = (f"no {subj.label} {what} any {ref.label}" if kind != "far" else
                f"every {subj.label} {what} every {ref.label}" + (" (any two of them)" if subj == ref else ""))
    if kind == "far":        # "far" is written as "no pair nearer than"
        score = _pair_score("near")
    key = f"{subj.key}_{kind}_{ref.key}" + ("" if quant == SOME else f"_{quant}")
    params = _params(kind, value)
    return Check(key, desc, head + score + tail, params, PRIMARY_WEIGHT, phrase, (subj, ref), kind, params[0].name,
                 scope=quant)


def between_check(subj: Entity, a: Entity, b: Entity, phrase: str) -> Check:
    body = f"""    xs, a_s, b_s = {_objects(subj)}, {_objects(a)}, {_objects(b)}
    d = scene.distance()
    d_ax, d_xb, d_ab = d.unsqueeze(3), d.unsqueeze(1), d.unsqueeze(2)   # [b, a, x, c]
    along = (d_ax ** 2 - d_xb ** 2 + d_ab ** 2) / (2 * d_ab.clamp(min=1e-3))   # x's foot on the line a -> c
    off_line = (d_ax ** 2 - along ** 2).clamp(min=0).sqrt()
    inside = scene.above(along, 0.0, scale=$BETWEEN_SCALE) * scene.below(along - d_ab, 0.0, scale=$BETWEEN_SCALE)
    ok = inside * scene.below(off_line, $BETWEEN_OFFSET, scale=$BETWEEN_SCALE)
    eye = torch.eye(scene.num_slots, dtype=torch.bool)
    valid = (a_s[:, :, None, None] & xs[:, None, :, None] & b_s[:, None, None, :]
             & ~eye[None, :, :, None] & ~eye[None, None, :, :] & ~eye[None, :, None, :])
    best = ok.masked_fill(~valid, 0.0).flatten(1).amax(dim=1)
    return torch.where(valid.flatten(1).any(dim=1), best, torch.zeros_like(best))
"""
    return Check(f"{subj.key}_between_{a.key}_and_{b.key}", f"a {subj.label} between a {a.label} and a {b.label} "
                 f"(its centre's foot on the line joining theirs lies between them, at most {BETWEEN_OFFSET:g} m "
                 f"off that line)", body,
                 [Param("BETWEEN_OFFSET", BETWEEN_OFFSET, "m: largest distance off the line", relax=0.3),
                  Param("BETWEEN_SCALE", 0.2, "m: softness", kind="scale")],
                 PRIMARY_WEIGHT, phrase, (subj, a, b), "between", "BETWEEN_OFFSET")


def _every(values: str) -> str:
    return f"""    has_any = torch.clamp(mask.float().sum(dim=1), max=1.0)
    ok = {values}
    return has_any * (0.5 * scene.all_of(ok, mask) + 0.5 * scene.mean_of(ok, mask))
"""


_ZONE_WORDS = {"front": "in front of it", "back": "behind it", "sides": "on both sides", "around": "all around"}


def object_check(kind: str, subj: Entity, quant: str, value: float, phrase: str) -> Check:
    """A requirement on each object of ``subj`` alone, for EVERY one (and at least one), SOME one, or NONE:
    ``wall`` (back within ``value`` m of a wall), ``wall_far`` (footprint at least ``value`` m from every wall),
    ``middle`` (centre within ``value`` m of the room's middle), ``centred_wall`` (back against a wall, centre
    within ``value`` m of the wall's middle), ``free_front`` / ``free_sides`` / ``free_around`` /
    ``free_back`` (a strip ``value`` m deep beyond those edges FREE_SHARE free)."""
    tests = {
        "wall": ("scene.below(scene.back_to_wall(), $WALL_GAP, scale=$WALL_SCALE)",
                 [Param("WALL_GAP", value, "m: largest gap between the back and the wall", relax=0.2),
                  Param("WALL_SCALE", 0.15, "m: softness", kind="scale")],
                 f"with its back within {value:g} m of a wall"),
        "wall_far": ("scene.above(scene.wall_distance(), $WALL_AWAY, scale=$WALL_SCALE)",
                     [Param("WALL_AWAY", value, "m: smallest gap to every wall", relax=-0.2),
                      Param("WALL_SCALE", 0.15, "m: softness", kind="scale")],
                     f"at least {value:g} m from every wall"),
        "middle": ("scene.below(scene.middle_offset, $MIDDLE_RADIUS, scale=$MIDDLE_SCALE)",
                   [Param("MIDDLE_RADIUS", value, "m: largest distance from the room's middle", relax=0.5),
                    Param("MIDDLE_SCALE", 0.3, "m: softness", kind="scale")],
                   f"with its centre within {value:g} m of the middle of the room"),
        "centred_wall": ("scene.below(scene.back_to_wall(), $WALL_GAP, scale=$WALL_SCALE) * "
                         "scene.below(scene.wall_offset(), $CENTRED_OFFSET, scale=$WALL_SCALE)",
                         [Param("CENTRED_OFFSET", value, "m: centre's largest offset from the wall's middle",
                                relax=0.3),
                          Param("WALL_GAP", 0.1, "m: largest gap between the back and the wall", relax=0.2),
                          Param("WALL_SCALE", 0.15, "m: softness", kind="scale")],
                         f"against a wall and centred on it (centre within {value:g} m of the wall's middle)"),
    }
    for zone in ("front", "sides", "around", "back"):
        tests[f"free_{zone}"] = (f"scene.above(scene.free_share($FREE_DEPTH, '{zone}'), $FREE_SHARE, "
                                 f"scale=$FREE_SCALE)",
                                 [Param("FREE_DEPTH", value, "m: depth of the free strip", relax=-0.2),
                                  Param("FREE_SHARE", FREE_SHARE, "share of the strip that must be free",
                                        relax=-0.15),
                                  Param("FREE_SCALE", 0.2, "softness (share)", kind="scale")],
                                 f"with a free strip {value:g} m deep {_ZONE_WORDS[zone]}")
    values, params, what = tests[kind]
    body = f"    mask = {_objects(subj)}\n"
    if quant == EVERY:
        body += _every(values)
        desc = f"every {subj.label} {what} (and there is at least one)"
    elif quant == SOME:
        body += f"    return scene.any_of({values}, mask)\n"
        desc = f"a {subj.label} {what}"
    else:                    # NONE, WITHOUT
        body += f"    return scene.all_of(1.0 - {values}, mask)\n"
        desc = f"no {subj.label} {what}"
    key = f"{subj.key}_{kind}" + ("" if quant == EVERY else f"_{quant}")
    return Check(key, desc, body, params, PRIMARY_WEIGHT, phrase, (subj,), kind, params[0].name, scope=quant)


def free_area_check(size: float, square: bool, middle: bool, phrase: str) -> Check:
    """A free circle of diameter ``size``, or a free square of side ``size`` (any orientation: a disk around
    it fits surely, half credit for the disk inside it), anywhere or within MIDDLE_RADIUS of the middle."""
    where = ", middle=MIDDLE_RADIUS" if middle else ""
    if square:
        test = (f"0.5 * scene.free_circle($FREE_SIZE / 2{where}).float() + 0.5 * scene.free_circle($FREE_SIZE * "
                f"math.sqrt(0.5){where}).float()")
        shape = f"a free {size:g} m square"
    else:
        test = f"scene.free_circle($FREE_SIZE / 2{where}).float()"
        shape = f"a free circle {size:g} m across"
    body = f"""    full = {test}
    # partial credit: a smaller free area at the same place
    smaller = scene.free_circle($FREE_SIZE / 2 * 0.75{where}).float()
    return 0.8 * full + 0.2 * smaller
"""
    params = [Param("FREE_SIZE", size, "m: side of the square / diameter of the circle", relax=-0.3)]
    if middle:
        params.append(Param("MIDDLE_RADIUS", MIDDLE_RADIUS, "m: its centre at most this far from the room's middle",
                            relax=0.5))
    return Check("free_area" + ("_middle" if middle else ""), shape + (" with its centre within "
                 f"{MIDDLE_RADIUS:g} m of the middle of the room" if middle else " anywhere on the floor"), body,
                 params, PRIMARY_WEIGHT, phrase, (), "free_area", "FREE_SIZE")


def room_size_check(lo: float | None, hi: float | None, phrase: str) -> Check:
    """The floor area between ``lo`` and ``hi`` square metres (None: no bound)."""
    params = [Param("AREA_MIN", lo if lo is not None else 0.0, "m^2: smallest floor area", relax=-2.0),
              Param("AREA_MAX", hi if hi is not None else 1e4, "m^2: largest floor area", relax=2.0),
              Param("AREA_SCALE", 2.0, "m^2: softness", kind="scale")]
    desc = ("a floor area " + (f"of at least {lo:g} m^2" if hi is None else f"of at most {hi:g} m^2" if lo is None
                               else f"between {lo:g} and {hi:g} m^2"))
    body = "    return scene.within(scene.floor_area, $AREA_MIN, $AREA_MAX, scale=$AREA_SCALE)\n"
    return Check("room_size", desc, body, params, SUPPORT_WEIGHT, phrase, (), "room_size",
                 "AREA_MIN" if lo is not None else "AREA_MAX")
