"""Exit codes of the bus commands (docs/CLI.md): 2 bad usage, 1 the work failed, 0 done or stopped;
and ``--bus URL`` the same way in each (signals: test_bus_shutdown.py)."""

from __future__ import annotations

import os

from stg_node.bus import Broker
from stg_node.cli import broker as broker_cli
from stg_node.cli import topic as topic_cli
from stg_node.cli.runner import EXIT_FAILED, EXIT_USAGE


def test_broker_bad_urls_are_usage_errors_and_nothing_is_bound(ipc_dir, capsys):
    assert broker_cli.main(["--bus", "http://nope"]) == EXIT_USAGE
    assert "ipc:///path" in capsys.readouterr().err
    assert broker_cli.main(["--bus", "ipc://" + ipc_dir + "/" + "x" * 120]) == EXIT_USAGE
    assert "too long" in capsys.readouterr().err
    assert broker_cli.main(["--bus", f"ipc://{ipc_dir}/bus", "--namespace", "bad space"]) == EXIT_USAGE
    assert broker_cli.main(["--bus", f"ipc://{ipc_dir}/bus", "--status-period", "often"]) == EXIT_USAGE
    assert os.listdir(ipc_dir) == []


def test_broker_that_cannot_serve_is_a_failure(ipc_url, capsys):
    with Broker(ipc_url, status_period_s=0):
        assert broker_cli.main(["--bus", ipc_url]) == EXIT_FAILED
    err = capsys.readouterr().err
    assert "stg-broker: error: a broker already serves" in err and "Traceback" not in err


def test_topic_usage_errors(ipc_url, capsys):
    assert topic_cli.main(["--bus", "tcp://host-without-port", "list"]) == EXIT_USAGE
    assert topic_cli.main(["--bus", ipc_url, "hz", "body/pose", "--window", "0"]) == EXIT_USAGE
    assert topic_cli.main(["--bus", ipc_url, "--namespace", "a b", "echo", "x"]) == EXIT_USAGE
    assert topic_cli.main(["--bus", ipc_url, "frobnicate"]) == EXIT_USAGE
    assert capsys.readouterr().err.count("usage: stg-topic") == 4


def test_topic_that_cannot_connect_is_a_failure(tcp_url, tmp_path, capsys):
    keys = tmp_path / "no-keys"
    code = topic_cli.main(["--bus", tcp_url, "--keys", str(keys), "--key-name", "robot", "echo", "body/pose"])
    assert code == EXIT_FAILED
    err = capsys.readouterr().err
    assert "stg-topic: error:" in err and "not found" in err and "Traceback" not in err


def test_bus_option_is_spelled_the_same_in_every_bus_command():
    for parser in (broker_cli.build_parser(), topic_cli.build_parser()):
        options = {opt for action in parser._actions for opt in action.option_strings}
        assert {"--bus", "--namespace", "--keys", "--log-level"} <= options, parser.prog
