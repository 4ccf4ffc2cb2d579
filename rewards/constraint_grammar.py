"""The offline planner's grammar of the words that change a request's meaning (:mod:`rewards.constraint_reader`):
quantities, the scope of a relation (its quantifier: every, each, all, any, some, no, none, without; its negation:
not, never, don't ...), and the rules of the broader vocabulary (apart, closer than, between, behind, facing away,
toward, the middle of the room, centred on a wall, away from the walls, free space beside an object, a free square
or circle, the room's size). A rule reads ``r``, the reader's state; words it does not read stay uncovered, so the
planner reports them instead of guessing."""

from __future__ import annotations

import re

from .planner_checks import facing_check, near_check
from .planner_scope import (AWAY_ANGLE, BEHIND_DEPTH, CENTRED_OFFSET, EVERY, FREE_AREA, FREE_DEPTH, LARGE_ROOM,
                            MIDDLE_RADIUS, NONE, SMALL_ROOM, SOME, WALL_AWAY, WITHOUT, between_check, free_area_check,
                            object_check, pair_check, room_size_check)

_NUM = r"\d+(?:\.\d+)?"
_UNIT = r"(?:m|cm|mm|meters?|metres?|centimeters?|centimetres?|millimeters?|millimetres?|ft|feet|foot|degrees?|deg)"
QTY = rf"(?:{_NUM}) ?{_UNIT}\b"
_TO_METRES = {"cm": 0.01, "centimeter": 0.01, "centimetre": 0.01, "mm": 0.001, "millimeter": 0.001,
              "millimetre": 0.001, "ft": 0.3048, "feet": 0.3048, "foot": 0.3048}


def quantity(text: str) -> float:
    """The value of a quantity like ``90 cm`` in metres (degrees stay degrees)."""
    m = re.match(rf"({_NUM}) ?([a-z]+)", text.strip())
    value, unit = float(m.group(1)), m.group(2)
    return value * _TO_METRES.get(unit if unit == "feet" else unit.rstrip("s"), 1.0)


# --------------------------------------------------------------------------------------------------------
# Scope: the quantifier and the negation of a relation's subject
# --------------------------------------------------------------------------------------------------------

#: A quantifier just before the subject ("every chair", "all of the chairs", "no 2 pieces", "without a").
_QUANT = re.compile(r"\b(?P<w>every|each|all|any|some|at least 1|no|none|without)(?: (?:of|a|an|any))?"
                    r"(?: (?:the|my|our|these|those|its|their))?(?: (?:2|single))? $")
_QUANTS = {"every": EVERY, "each": EVERY, "all": EVERY, "any": EVERY, "some": SOME, "at least 1": SOME,
           "no": NONE, "none": NONE, "without": WITHOUT}
#: A negation between the subject and the relation ("the desk is not", "should never be").
_NEGATION = re.compile(r"\b(?:not|never|isn't|aren't|doesn't|don't|shouldn't|mustn't|cannot|can't|won't)\b")
#: A negated instruction before the subject in the same clause ("do not put the desk ...", "never place a").
_NEGATED_VERB = re.compile(r"\b(?:do not|don't|never|avoid) (?:put|place|position|have|putting|placing|having|"
                           r"positioning|set|setting|let)(?: (?:a|an|the|any))? $")


def scope(r, subject, start: int) -> tuple[str | None, list[tuple[int, int]]]:
    """The reading of "subject ... relation at ``start``": EVERY, SOME, NONE, or None (no quantifier or negation
    said: the rule's default), with the spans of the words that set it (to cover once the rule reads them).
    "Not every" and double negations are not read: their words stay uncovered."""
    spans, quant = [], None
    before = r.text[:subject.start]
    q = _QUANT.search(before)
    if q:
        quant = _QUANTS[q.group("w")]
        spans.append(q.span())
    verb = _NEGATED_VERB.search(before)
    negations = [(subject.end + n.start(), subject.end + n.end())
                 for n in _NEGATION.finditer(r.text[subject.end:start])]
    if verb:
        negations.append(verb.span())
    if negations:
        if quant in (EVERY, NONE, WITHOUT) or len(negations) > 1:
            return None, []
        quant = NONE
        spans += negations
    return quant, spans


def cover_all(r, spans) -> None:
    for s, e in spans:
        r.cover(s, e)


# --------------------------------------------------------------------------------------------------------
# Rules
# --------------------------------------------------------------------------------------------------------

def _mention_at(r, pos: int):
    """The object mentioned right at ``pos`` (after an article or a number of 2), else None."""
    m = re.compile(r"(?:the |a |an |2 |both |each |every |all |any )*").match(r.text, pos)
    return next((x for x in r.mentions if x.start == m.end()), None)


def _rule_free_space(r) -> None:
    """Free strips beside an object ("1 m of free space in front of the wardrobe", "keep the area around the bed
    clear") and free areas ("a free 2 m square", "an open circle 1.5 m across in the middle of the room")."""
    zones = {"in front of": "front", "behind": "back", "beside": "sides", "next to": "sides",
             "on both sides of": "sides", "on either side of": "sides", "around": "around", "all around": "around"}
    where = "|".join(sorted(zones, key=len, reverse=True))
    free = r"(?:free|clear|open|empty|unobstructed)"
    strip = [rf"\b(?:(?:at least )?(?P<q>{QTY}) (?:of )?)?(?:{free} (?:floor )?(?:space|area|floor|room)|"
             rf"(?:free )?clearance)(?: of (?P<q2>{QTY}))? (?P<where>{where}) ",
             rf"\b(?:the )?(?:space|area|floor) (?P<where>{where}) (?P<obj>[a-z ]+?) (?:is |stays |kept |remains )?"
             rf"(?:free|clear|open|empty|unobstructed)\b"]
    for k, pattern in enumerate(strip):
        for m in re.finditer(pattern, r.text):
            subject = _mention_at(r, m.end() if k == 0 else m.start("obj"))
            if subject is None:
                continue
            q = m.groupdict().get("q") or m.groupdict().get("q2")
            end = subject.end if k == 0 else m.end()
            check = object_check(f"free_{zones[m.group('where')]}", subject.entity, EVERY,
                                 quantity(q) if q else FREE_DEPTH, r.text[m.start():end])
            r.add(check, m.start(), end, subject)
    mid = r"(?P<mid> (?:in|at) the (?:middle|centre|center)(?: of the (?:room|bedroom|floor))?)?"
    size = r"(?:(?P<{0}>{1}) (?:by (?P<{0}2>{1}) )?(?:wide |across )?)?"
    area = (rf"\b{size.format('q', QTY)}{free} {size.format('qa', QTY)}(?:floor )?(?P<shape>square|"
            rf"circle|circular area|area|space|spot)(?: (?:(?:of|with a diameter of|of at least) )?(?P<q3>{QTY})"
            rf"(?: by (?P<q4>{QTY}))?)?(?: (?:across|wide|in diameter|diameter))?{mid}")
    for m in re.finditer(area, r.text):
        q = m.group("q") or m.group("qa") or m.group("q3")
        q2 = m.group("q2") or m.group("qa2") or m.group("q4")
        if any(r.covered[k] for k, (s, e, _) in enumerate(r.words) if s >= m.start() and e <= m.end()):
            continue
        if q is None and not (m.group("mid") or m.group("shape") in ("square", "circle")):
            continue                   # "free space" alone: not a size
        q = q or f"{FREE_AREA} m"
        if q2 is not None and quantity(q2) != quantity(q):
            continue                   # a rectangle: not read, its words stay uncovered
        square = m.group("shape") == "square" or q2 is not None
        r.add(free_area_check(quantity(q), square, bool(m.group("mid")), m.group()), m.start(), m.end())


#: Words between the objects and "... apart" / "closer than", and between two objects joined by "and".
_LINK = re.compile(r"(?: (?:should|must|shall|to|be|are|is|all|always|each|both|not|never|do|does|don't|kept|keep))* ?")
_AND = re.compile(r" and (?:the |a |an )?")


def _rule_apart(r) -> None:
    """Distances between any two objects: "at least 1 m between any 2 pieces of furniture", "no 2 chairs closer
    than 0.5 m", "the desk and the bed at least 2 m apart", "the chair and the desk at most 1 m apart"."""
    for m in re.finditer(rf"\b(?:at least|a minimum of|no less than|minimum) (?P<q>{QTY}) (?:of (?:space|clearance|"
                         rf"free space|room) )?between (?P<quant>any|all|every|each)? ?(?:2 )?(?:pairs? of )?",
                         r.text):
        subject = _mention_at(r, m.end())
        if subject is not None and subject.start == m.end():
            r.add(pair_check("far", subject.entity, subject.entity, NONE, quantity(m.group("q")),
                             r.text[m.start():subject.end]), m.start(), subject.end, subject)
    for m in re.finditer(rf"\b(?:(?:is|are|be|stand|stands|standing|placed|put) )?(?P<cmp>at least|no less than|more "
                         rf"than|at most|no more than|less than|within) (?P<q>{QTY}) (?:apart|from each other|of each "
                         rf"other|from one another)\b|\b(?:(?:is|are|be|stand|stands|standing|placed|put) )?(?:closer|"
                         rf"nearer) than (?P<q2>{QTY})(?: (?:apart|to each other|from each other|to one another))?",
                         r.text):
        mentions = [x for x in r.mentions if x.end <= m.start()]
        if not mentions or not _LINK.fullmatch(r.text[mentions[-1].end:m.start()]):
            continue                   # the objects must come right before: "X (and Y) should be ... apart"
        subject = ref = mentions[-1]
        if len(mentions) > 1 and _AND.fullmatch(r.text[mentions[-2].end:ref.start]):
            subject = mentions[-2]
        end = m.end()
        to = re.compile(r" (?:to|from) ").match(r.text, m.end())   # "no X closer than d to Y"
        if to:
            other = _mention_at(r, to.end())
            if other is None or ref is not subject:
                continue
            ref, end = other, other.end
        quant, spans = scope(r, subject, m.start())
        close = m.group("q2") is not None or m.group("cmp") in ("at most", "no more than", "less than", "within")
        value = quantity(m.group("q") or m.group("q2"))
        if m.group("q2") is not None and quant == NONE:          # no 2 X closer than d: every pair d apart
            check = pair_check("far", subject.entity, ref.entity, NONE, value, m.group())
        elif not close and quant in (None, EVERY):                  # (all) X at least d apart
            check = pair_check("far", subject.entity, ref.entity, NONE, value, m.group())
        elif close and quant is None and ref is not subject:        # X and Y at most d apart
            check = near_check(subject.entity, ref.entity, value, m.group())
        else:
            continue
        cover_all(r, spans)
        r.add(check, m.start(), end, subject, ref)


def _rule_between(r) -> None:
    """"X between the A and the B", "X between the 2 beds"."""
    for m in re.finditer(r"\bbetween ", r.text):
        a = _mention_at(r, m.end())
        subject = r.before(m.start())
        if a is None or subject is None or r.covered[_word_at(r, m.start())]:
            continue
        rest = re.compile(r" and ").match(r.text, a.end)
        b = _mention_at(r, rest.end()) if rest else a if re.search(r"\b(?:2|both)\b", r.text[m.end():a.start]) else None
        if b is None:
            continue
        r.add(between_check(subject.entity, a.entity, b.entity, r.text[m.start():b.end]), m.start(), b.end,
              subject, a, b)


def _rule_direction(r) -> None:
    """"X faces away from Y" / "with its back to Y", "X turned toward Y" (facing), "X behind Y", with scope."""
    rules = [(r"\b(?:fac(?:es|e|ing)|turned|turns?|points?|pointing|oriented) away from\b|\bwith (?:its|their) "
              r"backs? (?:to|towards?)\b", "away", AWAY_ANGLE),
             (r"\b(?:turned|turns?|pointing|points?|oriented|angled) (?:towards?|to)\b", "facing", 30.0),
             (r"\b(?:directly )?behind\b", "behind", BEHIND_DEPTH)]
    for pattern, kind, value in rules:
        for m in re.finditer(pattern, r.text):
            subject = r.before(m.start())
            ref = r.reference_after(m.end(), subject)
            if subject is None or ref is None or r.covered[_word_at(r, m.start())]:
                continue
            quant, spans = scope(r, subject, m.start())
            if kind == "facing" and quant is None:
                check = facing_check(subject.entity, ref.entity, value, m.group())
            else:
                check = pair_check(kind, subject.entity, ref.entity, quant or SOME, value, m.group())
            cover_all(r, spans)
            r.add(check, m.start(), m.end(), subject, ref)


def _word_at(r, pos: int) -> int:
    return next(k for k, (s, e, _) in enumerate(r.words) if s <= pos < e)


def _rule_places(r) -> None:
    """The middle of the room, centred on a wall, away from / at least d from the walls, with scope."""
    walls = r"(?:the |a |one |all |every |any )?walls?\b"
    rules = [(rf"\b(?:centred|centered|in the (?:middle|centre|center)) (?:on|against|along|of) {walls}",
              "centred_wall", CENTRED_OFFSET),
             (r"\b(?:(?:is|are|be|stands?|placed) )?(?:in|at) the (?:middle|centre|center)(?: of the (?:room|bedroom|"
              r"floor))?\b|\b(?:centred|centered)(?: in the (?:room|bedroom))?\b", "middle", MIDDLE_RADIUS),
             (rf"\b(?:(?P<cmp>at least|no less than|more than) (?P<q>{QTY}) (?:away )?|away )from {walls}", "wall_far",
              WALL_AWAY)]
    for pattern, kind, value in rules:
        for m in re.finditer(pattern, r.text):
            if any(r.covered[k] for k, (s, e, _) in enumerate(r.words) if s >= m.start() and e <= m.end()):
                continue
            subject = r.before(m.start())
            if subject is None:
                continue
            quant, spans = scope(r, subject, m.start())
            q = m.groupdict().get("q")
            cover_all(r, spans)
            r.add(object_check(kind, subject.entity, quant or EVERY, quantity(q) if q else value, m.group()),
                  m.start(), m.end(), subject)


def _rule_room_size(r) -> None:
    """"a small / large / spacious bedroom", "at least 15 square metres"."""
    for m in re.finditer(r"\b(?P<w>small|compact|tiny|little|large|big|spacious|roomy|generous) (?:bed)?room\b",
                         r.text):
        small = m.group("w") in ("small", "compact", "tiny", "little")
        r.add(room_size_check(None if small else LARGE_ROOM, SMALL_ROOM if small else None, m.group()),
              m.start(), m.end())
    for m in re.finditer(r"\b(?P<cmp>at least|more than|over|at most|less than|under|no more than|no less than) "
                         rf"(?P<n>{_NUM}) ?(?:square (?:metres|meters|m)|sq ?m|m2)\b", r.text):
        n = float(m.group("n"))
        low = m.group("cmp") in ("at least", "more than", "over", "no less than")
        r.add(room_size_check(n if low else None, None if low else n, m.group()), m.start(), m.end())


#: The rules of this module, in the order the reader runs them (before its own distance and relation rules,
#: whose words these may contain: "free space next to", "at least 1 m from the walls").
GRAMMAR_RULES = (_rule_free_space, _rule_room_size, _rule_apart, _rule_between, _rule_places, _rule_direction)
