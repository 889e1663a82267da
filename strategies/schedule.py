"""The compact schedule string: any curriculum in one line.

Grammar (whitespace ignored)::

    schedule := item ("," item)*
    item     := stage | "(" schedule ")" "x" COUNT
    stage    := GROUPS ":" ITERATIONS ["@" WINDOW] ["/" CAMERAS "x" FRAMES] ["~" LOSSES]

* ``GROUPS``: letters from X, A, S, M and G (= X + A), e.g. ``XAS``, ``SG``. ``[S]`` fits v0
  only when it did not start from a measurement (the stage-0 ballistic estimate or a given v0)
  and holds it when it did, set per clip when the fit starts (e.g. ``XA[S]M``; see
  :attr:`strategies.base.Stage.velocity_if_unmeasured`).
* ``ITERATIONS``: iterations of the stage.
* ``@WINDOW``: only the first WINDOW training frames (default: all training frames); ``@ff``: the
  frames before ground contact, set per clip when the fit starts (at least 3; see
  :data:`strategies.base.FREE_FLIGHT`).
* ``/CxF``: C cameras and F frames per iteration (default: all; ``*`` keeps the default).
* ``~LOSSES``: ``img``, ``geo`` or ``img+geo`` (default both).

Examples: ProJo4D on an elastic scene is ``XAS:100@3/3x3,XASM:150/3x20``; GIC's sequential
schedule ``S:100@3/3x3~geo,M:150/3x20,A:40000/1x1``; a cyclic one ``XA:50,(S:25@3,M:25,A:25)x4``.
"""

from __future__ import annotations

import re

from strategies.base import FREE_FLIGHT, Stage, StrategyError, expand_groups

__all__ = ["parse_schedule", "format_stage"]

_STAGE = re.compile(
    r"^(?P<groups>[XAMG]*(?:\[S\])?[XASMG]*):(?P<iters>\d+)"
    r"(?:@(?P<window>\d+|ff))?"
    r"(?:/(?P<cams>\d+|\*)x(?P<frames>\d+|\*))?"
    r"(?:~(?P<losses>img\+geo|geo\+img|img|geo))?$"
)
_LOSS_NAMES = {"img": ("image",), "geo": ("geometry",), "img+geo": ("image", "geometry"), "geo+img": ("image", "geometry")}


def parse_schedule(text: str) -> list[Stage]:
    """Parse a schedule string into stages (repeats expanded).

    Raises:
        StrategyError: naming the offending part and what was expected.
    """
    if not isinstance(text, str) or not text.strip():
        raise StrategyError("empty schedule string; expected e.g. 'XAS:100@3,XASM:150'")
    s = re.sub(r"\s+", "", text)
    stages, pos = _parse_items(s, 0, text)
    if pos != len(s):
        raise StrategyError(f"unexpected {s[pos:]!r} at position {pos} of schedule {text!r}")
    return stages


def _parse_items(s: str, pos: int, original: str) -> tuple[list[Stage], int]:
    out: list[Stage] = []
    while True:
        if pos < len(s) and s[pos] == "(":
            inner, pos = _parse_items(s, pos + 1, original)
            if pos >= len(s) or s[pos] != ")":
                raise StrategyError(f"missing ')' in schedule {original!r}")
            m = re.match(r"x(\d+)", s[pos + 1:])
            if not m or int(m.group(1)) < 1:
                raise StrategyError(f"a group '(...)' must be followed by a repeat count 'xN' (N >= 1) in schedule {original!r}")
            out.extend(inner * int(m.group(1)))
            pos += 1 + m.end()
        else:
            end = pos
            while end < len(s) and s[end] not in ",()":
                end += 1
            token = s[pos:end]
            out.append(_parse_stage(token, original))
            pos = end
        if pos < len(s) and s[pos] == ",":
            pos += 1
            continue
        return out, pos


def _parse_stage(token: str, original: str) -> Stage:
    m = _STAGE.match(token)
    if not m:
        hint = ""
        head = token.split(":")[0].replace("[S]", "")
        if ":" not in token:
            hint = " (missing ':ITERATIONS')"
        elif "[" in head or "]" in head or token.split(":")[0].count("[S]") > 1:
            hint = " (only v0 can be conditional: '[S]', once)"
        elif head and set(head) - set("XASMG"):
            bad = sorted(set(head) - set("XASMG"))
            hint = f" (unknown group letter(s) {bad}: use X, A, S, M, G)"
        raise StrategyError(
            f"malformed stage {token!r} in schedule {original!r}{hint}; expected GROUPS:ITERATIONS[@WINDOW][/CxF][~img|geo] "
            "(WINDOW a frame count or 'ff', the frames before ground contact; '[S]' in GROUPS: v0 held when measured), "
            "e.g. 'XAS:100@3/3x3' or 'XA[S]M:150'"
        )
    iters = int(m.group("iters"))
    if iters < 1:
        raise StrategyError(f"stage {token!r} in schedule {original!r} needs at least 1 iteration")
    window = m.group("window")
    window = FREE_FLIGHT if window == "ff" else int(window) if window else None
    if window == 0:
        raise StrategyError(f"stage {token!r}: the frame window must be >= 1")
    cams = frames = None
    if m.group("cams"):
        cams = None if m.group("cams") == "*" else int(m.group("cams"))
        frames = None if m.group("frames") == "*" else int(m.group("frames"))
        if cams == 0 or frames == 0:
            raise StrategyError(f"stage {token!r}: cameras and frames per iteration must be >= 1")
    losses = _LOSS_NAMES[m.group("losses")] if m.group("losses") else ("image", "geometry")
    letters = m.group("groups")
    conditional = "[S]" in letters
    letters = letters.replace("[S]", "")
    if not letters:
        raise StrategyError(f"stage {token!r} in schedule {original!r} needs a parameter group besides '[S]' (X, A, M or G)")
    groups = expand_groups(letters)
    if conditional and "S" in groups:
        raise StrategyError(f"stage {token!r} in schedule {original!r} fits v0 both always (S) and only when not measured ([S])")
    return Stage(groups, iters, frames=window, cameras_per_step=cams, frames_per_step=frames, losses=losses,
                 velocity_if_unmeasured=conditional)


def format_stage(stage: Stage) -> str:
    """The schedule-string form of one stage (inverse of parsing)."""
    out = stage.groups_label() + f":{stage.iterations}"
    if stage.frames:
        out += f"@{stage.window_label()}"
    if stage.cameras_per_step or stage.frames_per_step:
        out += f"/{stage.cameras_per_step or '*'}x{stage.frames_per_step or '*'}"
    if tuple(stage.losses) != ("image", "geometry"):
        out += "~" + "+".join({"image": "img", "geometry": "geo"}[l] for l in stage.losses)
    return out
