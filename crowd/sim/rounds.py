"""A survivor's rounds against the crowd: the game's rules between the player's character
(crowd.sim.player) and the crowd (crowd.sim.ai), plain numpy. The pipeline plays them each frame (its GL
stages draw the result) and ``crowd-bench rounds`` plays them without GL, so both follow one set of rules.

A frame of the game: ``move_survivor`` (the survivor moves first: the zombies chase where it is now), the
crowd's step, then ``settle`` (the blows the zombies landed, and the survivor's own where its swing
landed). A round ends when the survivor is down; the next starts with a new crowd around it
(``Survivor.new_round``), and each round's length, kills, blows and end are kept (``Survivor.history``).
"""

from __future__ import annotations

from .player import STRIKE_REACH


def move_survivor(ai, survivor, dt: float, obstacles=None) -> bool:
    """The survivor's step within the crowd's world (and out of its obstacles); the crowd's player point
    follows it. Returns whether its swing landed in this step."""
    half = ai.half_extent
    landed = survivor.step(dt, (ai.origin - half, ai.origin + half))
    if obstacles is not None:  # it does not walk through walls either
        survivor.collide(ai.keep_out, obstacles)
    ai.player = survivor.position.copy()
    return landed


def settle(ai, survivor, landed: bool, blows_seen: int) -> int:
    """After the crowd's step: the survivor takes the blows landed since `blows_seen`, and its landed
    swing sweeps every living zombie within STRIKE_REACH in front of it. Returns the blows seen now."""
    survivor.hurt(ai.player_hits_taken - blows_seen)
    if landed:
        survivor.kills += ai.hit(ai.alive_in_front(survivor.position, STRIKE_REACH, survivor.heading))
    return ai.player_hits_taken
