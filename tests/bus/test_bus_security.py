"""CURVE on tcp: authorised keys talk; unauthorised peers receive nothing and cannot publish."""

from __future__ import annotations

import os
import stat
import threading
import time

import pytest
import zmq
import zmq.auth
from bushelpers import recv_until, sample_messages

from stg_node.bus import BodyPose, Broker, BusConfig, Publisher, Subscriber, ViewRequest, security
from stg_node.cli import keys as keys_cli


@pytest.fixture
def keydir(tmp_path):
    root = tmp_path / "keys"
    assert keys_cli.main(["init", str(root)]) == 0
    assert keys_cli.main(["add", str(root), "node"]) == 0
    assert keys_cli.main(["add", str(root), "robot"]) == 0
    return root


@pytest.fixture
def rogue(tmp_path):
    """A well-formed key pair the broker has never heard of."""
    root = tmp_path / "rogue"
    security.init_keys(root)
    security.add_client(root, "rogue")
    return root


def _curve(sock, client_secret_file, server_public_file):
    public, secret = zmq.auth.load_certificate(client_secret_file)
    server_public, _ = zmq.auth.load_certificate(server_public_file)
    sock.curve_secretkey, sock.curve_publickey, sock.curve_serverkey = secret, public, server_public


def test_stg_keys_makes_private_secrets_and_manages_the_list(keydir, capsys):
    assert security.authorized_names(keydir) == ["node", "robot"]
    for path in [keydir / "server.key_secret", keydir / "clients" / "node.key_secret"]:
        assert stat.S_IMODE(os.stat(path).st_mode) == 0o600
    assert keys_cli.main(["revoke", str(keydir), "robot"]) == 0
    assert keys_cli.main(["list", str(keydir)]) == 0
    assert capsys.readouterr().out.strip().splitlines()[-1] == "node"
    assert keys_cli.main(["revoke", str(keydir), "robot"]) == 1
    assert keys_cli.main(["authorize", str(keydir), str(keydir / "clients" / "robot.key")]) == 0
    assert security.authorized_names(keydir) == ["node", "robot"]
    assert keys_cli.main(["add", str(keydir), "node"]) == 1  # exists already: refused
    assert keys_cli.main(["init", str(keydir)]) == 1  # would replace the broker's keys


def _publish_until(stop: threading.Event, config: BusConfig, msg) -> None:
    with Publisher(config, node="authorised") as pub:
        while not stop.is_set():
            pub.publish(msg)
            stop.wait(0.01)


def test_authorised_clients_talk_and_outsiders_receive_nothing(tcp_url, keydir, rogue, ctx):
    node = BusConfig(url=tcp_url, keys=keydir, key_name="node")
    endpoint = node.endpoint("reliable", "out")
    with Broker(tcp_url, keys=keydir, status_period_s=0):
        plain = ctx.socket(zmq.SUB)  # no CURVE at all
        stranger = ctx.socket(zmq.SUB)  # CURVE with a key that is not authorised
        _curve(stranger, rogue / "clients" / "rogue.key_secret", keydir / "server.key")
        robot = ctx.socket(zmq.SUB)  # authorised, raw pyzmq as proto/README.md shows
        _curve(robot, keydir / "clients" / "robot.key_secret", keydir / "server.key")
        for sock in (plain, stranger, robot):
            sock.linger = 0
            sock.connect(endpoint)
            sock.subscribe(b"body/pose")
        stop = threading.Event()
        thread = threading.Thread(target=_publish_until, args=(stop, node, sample_messages()["BodyPose"]))
        thread.start()
        try:
            with Subscriber(node, [BodyPose], context=ctx) as ours:
                assert isinstance(ours.recv(timeout=30), BodyPose)
            assert robot.poll(30_000), "the authorised raw subscriber got nothing"
            assert robot.recv_multipart()[0] == b"body/pose"
            time.sleep(0.5)  # outsiders had every chance
            assert not plain.poll(0) and not stranger.poll(0)
        finally:
            stop.set()
            thread.join(5)


def test_outsiders_cannot_publish(tcp_url, keydir, rogue, ctx):
    node = BusConfig(url=tcp_url, keys=keydir, key_name="node")
    view = sample_messages()["ViewRequest"]
    from stg_node.bus.codec import encode

    with Broker(tcp_url, keys=keydir, status_period_s=0), Subscriber(node, [ViewRequest], context=ctx) as sub:
        stranger = ctx.socket(zmq.PUB)
        _curve(stranger, rogue / "clients" / "rogue.key_secret", keydir / "server.key")
        plain = ctx.socket(zmq.PUB)
        for sock in (stranger, plain):
            sock.linger = 0
            sock.connect(node.endpoint("reliable", "in"))
        with Publisher(node, node="authorised") as pub:
            assert pub.wait_for_subscribers("avatar/view")
            deadline = time.monotonic() + 1.0
            while time.monotonic() < deadline:
                stranger.send_multipart(encode(view, topic="avatar/view", seq=0, src="stranger", stamp_ns=1))
                plain.send_multipart(encode(view, topic="avatar/view", seq=0, src="plain", stamp_ns=1))
                time.sleep(0.01)
            pub.publish(view)
            got: list = []
            assert recv_until(sub, lambda m: m.header.src == "authorised", 30, got)
            got += list(sub.messages(timeout=0.3))  # anything else that was on its way
    assert [m.header.src for m in got] == ["authorised"]


def test_ipc_stays_open_by_default_next_to_curve_tcp(ipc_url, tcp_url, keydir, ctx):
    with Broker([ipc_url, tcp_url], keys=keydir, status_period_s=0):
        local = BusConfig(url=ipc_url, keys=keydir)  # keys given, but ipc: no CURVE (no key name needed)
        assert not local.secure
        with (
            Publisher(local, context=ctx) as pub,
            Subscriber(BusConfig(url=ipc_url), [BodyPose], context=ctx) as sub,
        ):
            assert pub.wait_for_subscribers("body/pose")
            pub.publish(sample_messages()["BodyPose"])
            assert isinstance(sub.recv(timeout=30), BodyPose)


def test_curve_on_ipc_when_asked(ipc_url, keydir, ctx):
    with Broker(ipc_url, keys=keydir, curve_on_ipc=True, status_period_s=0):
        plain = ctx.socket(zmq.SUB)
        plain.connect(BusConfig(url=ipc_url).endpoint("reliable", "out"))
        plain.subscribe(b"")
        keyed = BusConfig(url=ipc_url, keys=keydir, key_name="node", curve_on_ipc=True)
        with Publisher(keyed, context=ctx) as pub, Subscriber(keyed, [BodyPose], context=ctx) as sub:
            assert pub.wait_for_subscribers("body/pose")
            pub.publish(sample_messages()["BodyPose"])
            assert isinstance(sub.recv(timeout=30), BodyPose)
            assert not plain.poll(300)


def test_missing_keys_are_clear_errors(tcp_url, keydir, tmp_path):
    with pytest.raises(ValueError, match="key name"):
        Subscriber(BusConfig(url=tcp_url, keys=keydir), [BodyPose])
    with pytest.raises(security.MissingKeyError, match="nobody"):
        Subscriber(BusConfig(url=tcp_url, keys=keydir, key_name="nobody"), [BodyPose])
    with pytest.raises(security.MissingKeyError, match="broker secret key"):
        Broker(tcp_url, keys=tmp_path / "empty", status_period_s=0)
