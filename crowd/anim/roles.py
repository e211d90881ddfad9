"""Clip roles: which clip of a character plays idle, walk, run, attack, hit and death.

The built-in zombie names its clips after their roles (its walk is "shamble"); imported models use
whatever their artist typed ("Walk", "Walking", "Zombie_Walk", "clip0"). Roles are matched by name,
and any of them can be overridden: ``parse_overrides("walk=Walk_Gun,idle=Idle")``.

Matching, per role: a clip whose lower-cased name equals a role word wins, then one that starts with
it, then one that contains it; among equals the shortest name ("Run" before "Run_Gun"). Roles with
no match fall back: walk → idle, else the first looping clip that is not an action (an action clip only
where nothing else is), idle and run → walk; the actions (attack, hit, death) stay unassigned and are
simply not played. Only assigned clips are baked.
"""

from __future__ import annotations

from ..errors import CrowdError
from .bake import DEFAULT_BOUND_MM, DEFAULT_FPS

ROLES = ("idle", "walk", "run", "attack", "hit", "death")
ACTIONS = ("attack", "hit", "death")
ROLE_WORDS = {
    "idle": ("idle", "stand", "breath"),
    "walk": ("walk", "shamble", "stroll", "shuffle"),
    "run": ("run", "sprint", "jog", "chase"),
    "attack": ("attack", "punch", "bite", "slash", "stab", "swing", "strike"),
    "hit": ("hit", "hurt", "damage", "react", "recoil", "flinch"),
    "death": ("death", "die", "dying", "dead"),
}


class RoleError(CrowdError, ValueError):
    """Bad role override; the message is one line."""


def parse_overrides(text: str | None) -> dict[str, str]:
    if not text:
        return {}
    out = {}
    for item in text.split(","):
        role, sep, clip = item.partition("=")
        role, clip = role.strip(), clip.strip()
        if not sep or not role or not clip:
            raise RoleError(f"role overrides look like 'walk=Walking,idle=Idle', got {item!r}")
        if role not in ROLES:
            raise RoleError(f"unknown role {role!r}; roles are {', '.join(ROLES)}")
        out[role] = clip
    return out


def _score(name: str, word: str) -> tuple | None:
    low = name.lower()
    if low == word:
        return (0, len(name))
    if low.startswith(word):
        return (1, len(name))
    if word in low:
        return (2, len(name))
    return None


def match_roles(clips, overrides: dict[str, str] | None = None) -> tuple[dict[str, str | None], list[str]]:
    """(role → clip name or None, notes). `clips` are model.Clip objects (name and loop are used)."""
    names = [c.name for c in clips]
    if not names:
        raise RoleError("the character has no clips")
    overrides = dict(overrides or {})
    for role, clip in overrides.items():
        if role not in ROLES:
            raise RoleError(f"unknown role {role!r}; roles are {', '.join(ROLES)}")
        if clip not in names:
            raise RoleError(f"role {role}: no clip named {clip!r}; clips are {', '.join(names)}")
    roles: dict[str, str | None] = {}
    notes: list[str] = []
    for role in ROLES:
        if role in overrides:
            roles[role] = overrides[role]
            continue
        best = None
        for rank, word in enumerate(ROLE_WORDS[role]):
            for name in names:
                s = _score(name, word)
                if s is not None and (best is None or (s[0], rank, s[1]) < best[0]):
                    best = ((s[0], rank, s[1]), name)
        roles[role] = best[1] if best else None
    if roles["walk"] is None:
        roles["walk"] = roles["idle"] or _fallback_walk(clips, roles)
        notes.append(f"no clip is named like a walk; walk plays {roles['walk']!r}")
    for role in ("idle", "run"):
        if roles[role] is None:
            roles[role] = roles["walk"]
            notes.append(f"no {role} clip; {role} plays the walk {roles['walk']!r}")
    for role in ("attack", "hit", "death"):
        if roles[role] is None:
            notes.append(f"no {role} clip; agents will not {({'attack': 'attack', 'hit': 'react to hits', 'death': 'die'})[role]}")
    return roles, notes


def _fallback_walk(clips, roles: dict[str, str | None]) -> str:
    """The clip a character without an idle or a walk moves with: the first looping clip that is not an
    action (one the attack, hit or death role took, or named like one), else the first clip that is not
    an action, else the first looping clip, else the first clip. A creature whose clips are a bite, a
    death, a hit and a flying loop flies."""
    taken = {roles[r] for r in ACTIONS if roles[r]}
    action = {c.name for c in clips if c.name in taken or any(_score(c.name, w) for r in ACTIONS for w in ROLE_WORDS[r])}
    ranked = sorted(range(len(clips)), key=lambda k: (clips[k].name in action, not clips[k].loop, k))
    return clips[ranked[0]].name


def clips_used(roles: dict[str, str | None]) -> list[str]:
    """Distinct clip names the roles need, in role order: what the bake must hold, nothing more."""
    out: list[str] = []
    for role in ROLES:
        name = roles.get(role)
        if name and name not in out:
            out.append(name)
    return out


def bake_roles(character, roles: dict[str, str | None], fps: float | str = DEFAULT_FPS, precision: str = "f32",
               bound_mm: float = DEFAULT_BOUND_MM, report=None):
    """The bake of a character's role clips and nothing else: a scene bakes only what it plays
    (`report`: crowd.progress's callback)."""
    from .bake import bake

    return bake(character.skeleton, [character.clip(n) for n in clips_used(roles)], fps, precision, bound_mm=bound_mm, report=report)
