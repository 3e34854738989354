"""Scenes a user can write (issue 54, section 3): ``-o`` for every output folder, VTU frames that ParaView
warps once, ``translate``/``rotate``/``scale`` placing a ``[[body]]``, and any law of ``--material`` as a
``material`` table; the done-when run: a placed neo-Hookean box dropped on a plane by
``rtfem simulate scene.toml --duration T -o DIR`` rests on it with the plane carrying its weight."""

from __future__ import annotations

import pytest

from rtfem.cli.main import build_parser


@pytest.mark.parametrize("argv", [["simulate"], ["simulate", "scene.toml"], ["pictures"], ["demo"], ["batch", "plan.toml"]])
def test_minus_o_is_the_short_form_of_out_wherever_an_output_folder_is_taken(argv):
    assert build_parser().parse_args([*argv, "-o", "DIR"]).out == "DIR"
    assert build_parser().parse_args([*argv, "--out", "DIR"]).out == "DIR"


def test_the_demo_script_takes_minus_o_too(monkeypatch, tmp_path):
    from rtfem.cli import demo

    seen = []
    monkeypatch.setattr(demo, "static_poke", seen.append)
    monkeypatch.setattr(demo, "probe_dynamics", lambda out: None)
    monkeypatch.setattr(demo, "haptic_session", lambda: None)
    assert demo.main(["-o", str(tmp_path / "d")]) == 0 and seen == [tmp_path / "d"]
