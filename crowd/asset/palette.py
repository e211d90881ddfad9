"""The built-ins' vertex colours: a Palette (the zombie's by default), and the colour functions the
tubes call for skin, legs, shoes, torso and shirt."""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from .mesh_builder import _smoothstep


@dataclasses.dataclass(frozen=True)
class Palette:
    """The vertex colours of a build: skin, trousers, shoes, shirt and blood (linear RGB)."""

    skin: tuple = (0.46, 0.55, 0.40)  # sickly grey-green
    pants: tuple = (0.22, 0.20, 0.24)
    shoes: tuple = (0.12, 0.10, 0.09)
    shirt: tuple = (0.55, 0.50, 0.40)
    blood: tuple = (0.35, 0.05, 0.04)
    eyes: tuple = (0.9, 0.85, 0.55)  # milky
    wounds: float = 0.45  # how much of a skin blotch is blood (0: clean skin)
    ragged: bool = True  # torn trouser hems over bare shins (False: trousers down to the shoes)


ZOMBIE_PALETTE = Palette()
BLOOD = np.array(ZOMBIE_PALETTE.blood)


def _skin_color(pos, u, seed=0, palette: Palette = ZOMBIE_PALETTE):
    blotch = _smoothstep((np.sin(pos[:, 0] * 41.0 + 1.3) * np.sin(pos[:, 1] * 37.0) * np.sin(pos[:, 2] * 53.0 + 0.7) - 0.55) * 4.0)
    c = np.array(palette.skin)[None] * (0.92 + 0.08 * np.sin(pos[:, 1] * 23.0))[:, None]
    c = c * (1.0 - palette.wounds * blotch[:, None]) + np.array(palette.blood)[None] * palette.wounds * blotch[:, None]
    return np.concatenate([c, np.ones((pos.shape[0], 1))], axis=1)


def _leg_color(pos, u, palette: Palette = ZOMBIE_PALETTE):
    skin = _skin_color(pos, u, palette=palette)[:, :3]
    c = np.where((pos[:, 1] > (0.22 if palette.ragged else 0.0))[:, None], np.array(palette.pants)[None], skin)
    if not palette.ragged:
        return np.concatenate([c, np.ones((pos.shape[0], 1))], axis=1)
    torn = (pos[:, 1] > 0.22) & (pos[:, 1] < 0.36)  # ragged trouser hems above bare shins
    ragged = np.sin(np.arctan2(pos[:, 2], pos[:, 0] - np.sign(pos[:, 0]) * 0.1) * 7.0) * 0.05 + 0.29
    c = np.where((torn & (pos[:, 1] < ragged))[:, None], skin, c)
    return np.concatenate([c, np.ones((pos.shape[0], 1))], axis=1)


def _foot_color(pos, u, palette: Palette = ZOMBIE_PALETTE):
    return np.concatenate([np.repeat(np.array(palette.shoes)[None], pos.shape[0], 0), np.ones((pos.shape[0], 1))], axis=1)


def _torso_color(pos, u, palette: Palette = ZOMBIE_PALETTE):
    c = np.where((pos[:, 1] < 1.0)[:, None], np.array(palette.pants)[None], _skin_color(pos, u, palette=palette)[:, :3])
    return np.concatenate([c, np.ones((pos.shape[0], 1))], axis=1)


def _shirt_color(pos, u, palette: Palette = ZOMBIE_PALETTE):
    stain = _smoothstep((np.sin(pos[:, 0] * 17.0) * np.sin(pos[:, 1] * 13.0 + 1.0) - 0.3) * 3.0)
    c = np.array(palette.shirt)[None] * (1.0 - 0.5 * stain[:, None]) + np.array(palette.blood)[None] * 0.5 * stain[:, None]
    return np.concatenate([c, np.ones((pos.shape[0], 1))], axis=1)


def _colors(palette: Palette):
    """The colour functions (skin, leg, foot, torso, shirt) of a palette, as the tubes call them."""
    return (functools.partial(_skin_color, palette=palette), functools.partial(_leg_color, palette=palette),
            functools.partial(_foot_color, palette=palette), functools.partial(_torso_color, palette=palette),
            functools.partial(_shirt_color, palette=palette))
