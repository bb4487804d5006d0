"""Every option of the ``glaciar`` command has help text, and its default is shown.

The parser is walked (every sub-command, every action except ``-h``), so an option added
later without help fails here.
"""
from __future__ import annotations

import argparse

import pytest

from glaciar.cli import build_parser


def _subparsers(parser):
    """(command name, sub-parser) of every sub-command of ``parser``."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            yield from action.choices.items()


def _options(parser):
    """Every action of ``parser`` except help and the sub-command dispatcher."""
    return [a for a in parser._actions
            if not isinstance(a, (argparse._HelpAction, argparse._SubParsersAction))]


PARSER = build_parser()
COMMANDS = dict(_subparsers(PARSER))
OPTIONS = [(name, a) for name, sp in COMMANDS.items() for a in _options(sp)] + \
          [("glaciar", a) for a in _options(PARSER)]


def _label(action):
    return "/".join(action.option_strings) or action.dest


def test_every_command_is_walked():
    # The walk reaches every sub-command the package documents (cli.py's docstring).
    assert set(COMMANDS) == {"demo", "init", "simulate", "status", "report", "fit", "next",
                             "catalog", "lf", "export"}
    assert len(OPTIONS) > 40


@pytest.mark.parametrize("command,action", OPTIONS,
                         ids=[f"{n}:{_label(a)}" for n, a in OPTIONS])
def test_option_has_help(command, action):
    assert action.help and action.help.strip(), f"glaciar {command} {_label(action)}: no help text"


def _help_line(command, action):
    """The option's help as ``glaciar COMMAND --help`` prints it (one line of text)."""
    parser = COMMANDS.get(command, PARSER)
    fmt = parser._get_formatter()
    return " ".join(fmt._expand_help(action).split()) if action.help else ""


@pytest.mark.parametrize("command,action",
                         [(n, a) for n, a in OPTIONS if a.nargs != 0],
                         ids=[f"{n}:{_label(a)}" for n, a in OPTIONS if a.nargs != 0])
def test_default_is_shown(command, action):
    # Options taking a value say what happens without them: the default value, or in words
    # when the default is None ("default: all CPUs").
    text = _help_line(command, action)
    where = f"glaciar {command} {_label(action)}: {text!r}"
    if action.default is None or action.default is argparse.SUPPRESS:
        if action.option_strings:          # a required positional has no default to state
            assert "default" in text.lower(), where
    else:
        assert str(action.default) in text and "default" in text.lower(), where


def test_formatted_help_shows_defaults():
    # The ones the issue named: demo's five options, --mode, --per-field, --seed.
    demo = COMMANDS["demo"].format_help()
    assert "(default: glaciar-demo)" in demo and "(default: 2018)" in demo
    sim = " ".join(COMMANDS["simulate"].format_help().split())
    assert "(default: windowed)" in sim
    fit = " ".join(COMMANDS["fit"].format_help().split())
    assert "separately" in fit and "(default: 0)" in fit


def test_fit_max_steps_help_matches_sampler_default():
    # The help quotes the sampler's cap; keep the two in step.
    from glaciar.inference.sampling import DEFAULT_MAX_STEPS

    for command in ("fit", "simulate"):
        (action,) = [a for a in _options(COMMANDS[command]) if "--max-steps" in a.option_strings]
        assert f"default: {DEFAULT_MAX_STEPS}" in action.help
