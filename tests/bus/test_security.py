"""Access control and TLS over real zenoh sessions on loopback: deploy/router-secure.json5 as shipped."""

from __future__ import annotations

import json
import shutil
import sys
import threading
import time

import pytest
import zenoh

from messages import topics
from services.runtime import deploy_file, load_config
from services.runtime.certs import write_certs
from tests.conftest import free_port, wait_until

MAP_UPDATE = topics.map_update()
MARKER = topics.places_confirmed()  # a key everyone may publish: sent after a map update, on the same link


class Heard:
    """Payloads heard on one key, from zenoh's threads."""

    def __init__(self, session: zenoh.Session, key: str) -> None:
        self._lock = threading.Lock()
        self.payloads: list[bytes] = []
        self._sub = session.declare_subscriber(key, self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self.payloads.append(sample.payload.to_bytes())

    def get(self) -> list[bytes]:
        with self._lock:
            return list(self.payloads)


def _tls_client(folder, endpoint: str) -> zenoh.Config:
    """deploy/client-secure.json5 with the certificate files of one identity's folder."""
    conf = load_config(deploy_file("client-secure.json5"), connect=[endpoint])
    for key, name in (("root_ca_certificate", "ca.pem"), ("connect_certificate", "cert.pem"),
                      ("connect_private_key", "key.pem")):
        conf.insert_json5(f"transport/link/tls/{key}", json.dumps(str(folder / name)))
    return conf


def _open_when_up(conf: zenoh.Config, timeout_s: float = 20.0) -> zenoh.Session:
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return zenoh.open(conf)
        except zenoh.ZError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)


@pytest.fixture
def tls_router(tmp_path, processes):
    """`relaxmap router --config deploy/router-secure.json5` in a folder holding its secrets/, on loopback.

    Yields (identity folders by name, endpoint).
    """
    folders = write_certs(tmp_path / "ca", ["relaxer", "robot", "viewer"])
    host = tmp_path / "router-host"
    shutil.copytree(folders["router"], host / "secrets")
    endpoint = f"tls/127.0.0.1:{free_port()}"
    proc = processes.start([sys.executable, "-m", "services.cli", "router", "--config",
                            str(deploy_file("router-secure.json5")), "--listen", endpoint], cwd=host)
    yield folders, endpoint
    assert processes.stop(proc) == 0
    out = proc.stdout.read().decode()
    assert "relaxmap router stopped" in out, out


def test_only_the_relaxer_identity_publishes_map_updates(tls_router):
    folders, endpoint = tls_router
    with (_open_when_up(_tls_client(folders["viewer"], endpoint)) as viewer,
          zenoh.open(_tls_client(folders["robot"], endpoint)) as robot,
          zenoh.open(_tls_client(folders["relaxer"], endpoint)) as relaxer):
        updates, markers = Heard(viewer, MAP_UPDATE), Heard(viewer, MARKER)
        # the viewer hears the robot's allowed messages, and the relaxer's map updates
        assert wait_until(lambda: (robot.put(MARKER, b"robot-ready"), b"robot-ready" in markers.get())[1], 20, 0.2)
        assert wait_until(lambda: (relaxer.put(MAP_UPDATE, b"relaxer"), b"relaxer" in updates.get())[1], 20, 0.2)
        # the robot's map update is dropped by the router; its marker, sent after it on the same link, is not
        robot.put(MAP_UPDATE, b"robot")
        robot.put(MARKER, b"after-robot-update")
        assert wait_until(lambda: b"after-robot-update" in markers.get(), 10)
        assert b"robot" not in updates.get()
        # a session's own subscriber is not behind the router: the robot hears itself, nobody else does
        relaxer_heard = Heard(relaxer, MAP_UPDATE)
        robot.put(MAP_UPDATE, b"robot-again")
        robot.put(MARKER, b"after-robot-again")
        assert wait_until(lambda: b"after-robot-again" in markers.get(), 10)
        assert b"robot-again" not in updates.get() and b"robot-again" not in relaxer_heard.get()


def test_only_the_relaxer_identity_serves_map_queries(tls_router):
    folders, endpoint = tls_router
    with (_open_when_up(_tls_client(folders["viewer"], endpoint)) as viewer,
          zenoh.open(_tls_client(folders["robot"], endpoint)) as robot,
          zenoh.open(_tls_client(folders["relaxer"], endpoint)) as relaxer):

        def answers(key: str) -> list[bytes]:
            return [r.ok.payload.to_bytes() for r in viewer.get(key, timeout=2.0) if r.ok is not None]

        health = topics.health(service="robot")
        robot.declare_queryable(health, lambda q: q.reply(q.key_expr, b"robot-health"))
        robot.declare_queryable(topics.map_stats(), lambda q: q.reply(q.key_expr, b"robot-stats"))
        # the robot's health queryable, declared after its map one on the same link, is reachable...
        assert wait_until(lambda: answers(health) == [b"robot-health"], 20, 0.2)
        # ...its map queryable is not, not even through a wildcard query
        assert answers(topics.map_stats()) == []
        assert answers("relaxmap/robot0/map/**") == []
        relaxer.declare_queryable(topics.map_stats(), lambda q: q.reply(q.key_expr, b"relaxer-stats"))
        assert wait_until(lambda: answers(topics.map_stats()) == [b"relaxer-stats"], 20, 0.2)
        # and anyone may ask the map
        assert [r.ok.payload.to_bytes() for r in robot.get(topics.map_stats(), timeout=2.0)
                if r.ok is not None] == [b"relaxer-stats"]


def test_a_client_without_a_valid_certificate_cannot_connect(tls_router, tmp_path):
    folders, endpoint = tls_router
    with _open_when_up(_tls_client(folders["viewer"], endpoint)) as viewer:
        markers = Heard(viewer, MARKER)
        # no certificate at all
        conf = _tls_client(folders["relaxer"], endpoint)
        conf.insert_json5("transport/link/tls/enable_mtls", "false")
        conf.insert_json5("transport/link/tls/connect_certificate", "null")
        conf.insert_json5("transport/link/tls/connect_private_key", "null")
        with pytest.raises(zenoh.ZError):
            zenoh.open(conf)
        # a certificate named `relaxer`, signed by another authority
        forged = write_certs(tmp_path / "other-ca", ["relaxer"])
        conf = _tls_client(forged["relaxer"], endpoint)
        conf.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(folders["relaxer"] / "ca.pem")))
        with pytest.raises(zenoh.ZError):
            zenoh.open(conf)
        # plain TCP to the TLS port
        plain = load_config(deploy_file("client.json5"), connect=[endpoint.replace("tls/", "tcp/")])
        with pytest.raises(zenoh.ZError):
            zenoh.open(plain)
        # a valid one still gets in
        with zenoh.open(_tls_client(folders["robot"], endpoint)) as robot:
            assert wait_until(lambda: (robot.put(MARKER, b"in"), b"in" in markers.get())[1], 20, 0.2)


def test_usrpwd_usernames_are_subjects_too(tmp_path):
    """The same access control with usernames (transport/auth/usrpwd) instead of certificates, over TCP."""
    (tmp_path / "credentials.txt").write_text("relaxer:relaxer-secret\nrobot:robot-secret\nviewer:viewer-secret\n")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    conf = load_config(deploy_file("router-secure.json5"), listen=[endpoint])
    conf.insert_json5("transport/link/protocols", '["tcp"]')
    conf.insert_json5("transport/link/tls", "{}")
    conf.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(tmp_path / "credentials.txt")))

    def client(user: str, password: str) -> zenoh.Config:
        c = load_config(deploy_file("client.json5"), connect=[endpoint])
        c.insert_json5("transport/auth/usrpwd", json.dumps({"user": user, "password": password}))
        return c

    with zenoh.open(conf):
        with pytest.raises(zenoh.ZError):
            zenoh.open(client("relaxer", "wrong"))
        with (zenoh.open(client("viewer", "viewer-secret")) as viewer,
              zenoh.open(client("robot", "robot-secret")) as robot,
              zenoh.open(client("relaxer", "relaxer-secret")) as relaxer):
            updates, markers = Heard(viewer, MAP_UPDATE), Heard(viewer, MARKER)
            assert wait_until(lambda: (relaxer.put(MAP_UPDATE, b"relaxer"), b"relaxer" in updates.get())[1], 20, 0.2)
            robot.put(MAP_UPDATE, b"robot")
            robot.put(MARKER, b"after-robot-update")
            assert wait_until(lambda: b"after-robot-update" in markers.get(), 10)
            assert b"robot" not in updates.get()
