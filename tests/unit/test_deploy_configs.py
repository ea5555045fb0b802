"""The zenoh files of deploy/, the split of the process graph across hosts, and `relaxmap certs`."""

from __future__ import annotations

import ipaddress
from pathlib import Path

import pytest
from cryptography import x509
from cryptography.x509.oid import NameOID

from services.launch.graph import load_graph
from services.launch.runner import RunError, local_part
from services.runtime import deploy_file, load_config
from services.runtime.certs import write_certs

DEPLOY = Path(deploy_file("graph.json")).parent


@pytest.mark.parametrize("name", sorted(p.name for p in DEPLOY.glob("*.json5")))
def test_every_shipped_zenoh_file_loads(name):
    conf = load_config(DEPLOY / name)
    mode = conf.get_json("mode").strip('"')
    expected = {"local-peer.json5": "peer", "router.json5": "router", "router-secure.json5": "router",
                "client.json5": "client", "client-secure.json5": "client"}
    assert mode == expected[name]
    assert conf.get_json("scouting/multicast/enabled") == "false"


def test_secure_files_allow_tls_only_and_the_router_denies_by_default():
    router = load_config(DEPLOY / "router-secure.json5")
    client = load_config(DEPLOY / "client-secure.json5")
    for conf in (router, client):
        assert conf.get_json("transport/link/protocols") == '["tls"]'
        assert conf.get_json("transport/link/tls/enable_mtls") == "true"
    assert router.get_json("access_control/enabled") == "true"
    assert router.get_json("access_control/default_permission") == '"deny"'


def test_local_part_of_the_graph():
    graph = load_graph(deploy_file("graph.json"))
    assert local_part(graph, only=[], skip=[], remote=False) is graph
    assert local_part(graph, only=["relaxer"], skip=[], remote=True).names() == ["relaxer"]
    rest = local_part(graph, only=[], skip=["relaxer", "recorder"], remote=True).names()
    assert rest == [n for n in graph.names() if n not in ("relaxer", "recorder")]
    with pytest.raises(RunError, match="--connect"):
        local_part(graph, only=["relaxer"], skip=[], remote=False)
    with pytest.raises(RunError, match="no service relaxr"):
        local_part(graph, only=["relaxr"], skip=[], remote=True)
    with pytest.raises(RunError, match="no service"):
        local_part(graph, only=[], skip=graph.names(), remote=True)


def test_certs_are_signed_by_one_ca_and_name_the_router_hosts(tmp_path):
    folders = write_certs(tmp_path, ["relaxer"], router_hosts=["10.0.0.1", "map.example"])
    ca = x509.load_pem_x509_certificate((tmp_path / "ca.pem").read_bytes())
    for name in ("router", "relaxer"):
        cert = x509.load_pem_x509_certificate((folders[name] / "cert.pem").read_bytes())
        cert.verify_directly_issued_by(ca)
        assert cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == name
        assert (folders[name] / "ca.pem").read_bytes() == (tmp_path / "ca.pem").read_bytes()
        assert (folders[name] / "key.pem").stat().st_mode & 0o077 == 0
    san = x509.load_pem_x509_certificate((folders["router"] / "cert.pem").read_bytes()).extensions.get_extension_for_class(
        x509.SubjectAlternativeName).value
    assert ipaddress.ip_address("10.0.0.1") in san.get_values_for_type(x509.IPAddress)
    assert {"map.example", "localhost"} <= set(san.get_values_for_type(x509.DNSName))
    # a second call adds identities under the same CA
    ca_before = (tmp_path / "ca.pem").read_bytes()
    more = write_certs(tmp_path, ["robot"])
    assert (tmp_path / "ca.pem").read_bytes() == ca_before
    x509.load_pem_x509_certificate((more["robot"] / "cert.pem").read_bytes()).verify_directly_issued_by(ca)
    with pytest.raises(ValueError, match="router"):
        write_certs(tmp_path, ["router"])
