"""The command line explains itself: help on every argument, the command list of docs/cli.md
checked against the parser, one way to give a pair of epochs (--pre/--post)."""
import argparse
import re
from pathlib import Path

import pytest

from quakescan.cli import build_parser, main

CLI_PAGE = Path(__file__).resolve().parents[1] / "docs" / "cli.md"
GLOBAL = "(global)"


def _commands(parser) -> dict:
    (sub,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    return dict(sub.choices)


def _arguments(parser) -> list:
    return [a for a in parser._actions if not isinstance(a, (argparse._HelpAction, argparse._SubParsersAction))]


def _parser_flags(parser, command: bool = True) -> list:
    """Each optional argument as the tuple of its option strings (-h left out, and in a
    command -q/--quiet, which docs/cli.md lists once with the global options)."""
    return [tuple(a.option_strings) for a in _arguments(parser)
            if a.option_strings and not (command and a.dest == "quiet")]


def _cli_page_entries() -> dict:
    """{command: text of its entry} from the code block of docs/cli.md's "The commands"
    section; an entry is a `quakescan …` line and its indented continuation lines, comments cut."""
    text = CLI_PAGE.read_text()
    section = text[text.index("## The commands\n"):]
    block = section[section.index("```sh\n") + 6:]
    block = block[:block.index("```")]
    entries: dict = {}
    current = None
    for line in block.splitlines():
        code = line.split("  # ")[0]
        if line.startswith("quakescan "):
            word = code.split()[1]
            current = GLOBAL if word.startswith("[") else word
            assert current not in entries, f"docs/cli.md lists {current} twice"
            entries[current] = code
        elif line.strip():
            assert current is not None and line.startswith(" "), f"docs/cli.md line outside an entry: {line!r}"
            entries[current] += " " + code
    return entries


def _listed_flags(text: str) -> set:
    return set(re.findall(r"(?<![\w-])(--?[a-z][a-z0-9-]*)", text))


def test_every_argument_of_every_command_has_help():
    parser = build_parser()
    missing = [f"{GLOBAL} {a.option_strings or a.dest}" for a in _arguments(parser) if not (a.help or "").strip()]
    for name, command in _commands(parser).items():
        assert (command.description or _help_of(parser, name)), f"{name}: no help"
        missing += [f"{name} {a.option_strings or a.dest}" for a in _arguments(command)
                    if not (a.help or "").strip()]
    assert not missing, f"arguments without help: {missing}"


def _help_of(parser, name: str) -> str:
    (sub,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    return next((c.help for c in sub._choices_actions if c.dest == name), "")


@pytest.mark.parametrize("flag,command", [("--threads", "classify"), ("--trees", "train"), ("--depth", "train"),
                                          ("--seed", "train"), ("--buffer", "import-cityjson")])
def test_help_shows_the_defaults_that_matter(flag, command):
    (action,) = [a for a in _arguments(_commands(build_parser())[command]) if flag in a.option_strings]
    assert "default" in action.help, f"{command} {flag}: {action.help!r}"


def test_cli_page_lists_every_command_and_flag_of_the_parser_and_no_other():
    parser = build_parser()
    entries = _cli_page_entries()
    commands = _commands(parser)
    assert set(entries) - {GLOBAL} == set(commands), "docs/cli.md's command list and the parser's commands differ"
    problems = []
    for name, command in [(GLOBAL, parser), *commands.items()]:
        named = _listed_flags(entries[name])
        flags = _parser_flags(command, command=name != GLOBAL)
        problems += [f"{name}: {'/'.join(f)} not in docs/cli.md" for f in flags if not set(f) & named]
        known = {s for f in flags for s in f}
        problems += [f"{name}: docs/cli.md names {f}, which the parser lacks" for f in sorted(named - known)]
    assert not problems, "\n".join(problems)


def test_cli_page_check_sees_a_flag_the_parser_lacks(monkeypatch):
    """The check above can fail: a docs/cli.md flag the parser does not have is reported."""
    entries = _cli_page_entries()
    assert "--no-such-flag" not in _listed_flags(entries["classify"])
    assert "--no-such-flag" in _listed_flags(entries["classify"] + " [--no-such-flag]")


def test_train_takes_pre_post_pairs_and_refuses_unmatched_ones(tmp_path, capsys):
    assert main(["train", "--pre", "a.las", "--pre", "b.las", "--post", "c.las", "-o", str(tmp_path / "m")]) == 2
    assert "train: 2 --pre and 1 --post" in capsys.readouterr().err
    assert main(["train", "-o", str(tmp_path / "m")]) == 2
    assert "no training pair" in capsys.readouterr().err


def test_robustness_takes_pre_post(tmp_path, capsys):
    assert main(["robustness", "--pre", "a", "-o", str(tmp_path / "r")]) == 2
    assert "--pre PRE_SCENE --post POST_SCENE" in capsys.readouterr().err


@pytest.mark.parametrize("argv,unrecognised", [
    (["train", "--pair", "a.las", "b.las", "-o", "m.skops"], "--pair a.las b.las"),
    (["calibrate-lod", "a.las", "b.las"], "a.las b.las"),
    (["robustness", "pre", "post", "-o", "report"], "pre post"),
])
def test_the_old_pair_forms_are_usage_errors(tmp_path, monkeypatch, capsys, argv, unrecognised):
    """The forms before --pre/--post (removed after 0.1) end in argparse's usage error, exit 2,
    naming what it did not recognise; nothing runs and nothing is written."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2
    out, err = capsys.readouterr()
    assert out == "" and err.startswith("usage: quakescan ")
    assert f"quakescan: error: unrecognized arguments: {unrecognised}" in err
    assert "Traceback" not in err and list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("argv, kind", [(["scan", "s", "-o", "a.las"], "uls"), (["dim", "s", "-o", "a.las"], "dim"),
                                        (["acquire", "s", "--kind", "als", "-o", "a.las"], "als")])
def test_scan_and_dim_are_acquire_of_the_built_in_kinds(argv, kind):
    from quakescan.cli.acquisition import cmd_acquire

    args = build_parser().parse_args(argv)
    assert args.func is cmd_acquire and args.kind == kind
    assert args.survey == (None if argv[0] == "acquire" else "paper")  # acquire: the sensor's default preset


def test_acquire_needs_a_kind(capsys):
    with pytest.raises(SystemExit) as e:
        build_parser().parse_args(["acquire", "s", "-o", "a.las"])
    assert e.value.code == 2 and "--kind" in capsys.readouterr().err
