"""Shell completion (issue 30.5): Click's, for commands, options, method names, config keys and paths."""

from __future__ import annotations

import os
import subprocess
import sys

from click.shell_completion import BashComplete

from condtrack_cli.cli import cli


def completions(args: list[str], incomplete: str) -> list[tuple[str, str]]:
    """(type, value) of what bash would be offered after ``condtrack ARGS INCOMPLETE``."""
    found = BashComplete(cli, {}, "condtrack", "_CONDTRACK_COMPLETE").get_completions(args, incomplete)
    return [(item.type, item.value) for item in found]


def test_commands_options_methods_and_config_keys_complete():
    assert completions([], "st") == [("plain", "stages"), ("plain", "status")]
    assert completions(["track"], "--ov") == [("plain", "--overlay"), ("plain", "--overlay-points")]
    assert completions(["track", "-m"], "c") == [("plain", "clf"), ("plain", "cnlf")]
    assert completions(["track", "--set"], "filter.cnlf.pa") == [("plain", "filter.cnlf.particles"),
                                                               ("plain", "filter.cnlf.path_lag"),
                                                               ("plain", "filter.cnlf.path_points")]
    assert ("plain", "motion.q_floor") in completions(["track", "--set"], "motion.")
    assert completions(["render", "--ellipses"], "") == [("plain", "all"), ("plain", "visible"), ("plain", "none")]
    assert completions(["track"], "sample") == [("file", "sample")]  # INPUT: the shell lists the paths
    assert completions(["status"], "tr") == [("dir", "tr")]


def test_the_console_script_prints_the_bash_script_and_answers_it():
    env = {**os.environ, "_CONDTRACK_COMPLETE": "bash_source"}
    main = [sys.executable, "-c", "import sys; from condtrack_cli.cli import main; sys.argv[0] = 'condtrack'; main()"]
    script = subprocess.run(main, env=env, capture_output=True, text=True, timeout=60)
    assert script.returncode == 0 and "complete -o nosort -F _condtrack_completion condtrack" in script.stdout
    env.update(_CONDTRACK_COMPLETE="bash_complete", COMP_WORDS="condtrack track -m s", COMP_CWORD="3")
    answer = subprocess.run(main, env=env, capture_output=True, text=True, timeout=60)
    assert answer.returncode == 0 and answer.stdout.split() == ["plain,stk"]
