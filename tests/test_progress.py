"""Progress of long work (crowd.progress, issue 22 point 6): a bar on a terminal, nothing where the
output is not one (CI, pipes), and the callback the panel's line reads."""

from __future__ import annotations

import io
import sys

from crowd.progress import bar, steps


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_a_terminal_gets_a_bar_and_a_pipe_gets_nothing(monkeypatch):
    terminal = _Terminal()
    monkeypatch.setattr(sys, "stderr", terminal)
    assert list(steps(range(5), desc="baking clips", unit="clip")) == list(range(5))
    assert "baking clips" in terminal.getvalue()
    pipe = io.StringIO()
    monkeypatch.setattr(sys, "stderr", pipe)
    assert list(steps(range(5), desc="baking clips")) == list(range(5))
    with bar(3, "starting") as b:
        b.update(3)
    assert pipe.getvalue() == ""


def test_the_callback_hears_each_step_and_the_end():
    heard = []
    assert list(steps(["a", "b", "c"], desc="compressing clips", report=lambda *a: heard.append(a))) == ["a", "b", "c"]
    assert heard == [(0, 3, "compressing clips"), (1, 3, "compressing clips"), (2, 3, "compressing clips"), (3, 3, "compressing clips")]
    heard.clear()
    assert list(steps(iter([]), desc="nothing", report=lambda *a: heard.append(a))) == []
    assert heard == [(0, 0, "nothing")]


def test_the_bake_reports_its_clips(zombie):
    from crowd.anim.roles import bake_roles, match_roles

    roles, _ = match_roles(zombie.clips, {})
    heard = []
    baked = bake_roles(zombie, roles, 30, "compressed", 0.5, report=lambda *a: heard.append(a))
    clips = len(baked.clips)
    assert (clips, clips, "baking clips") in heard and (clips, clips, "compressing clips") in heard
