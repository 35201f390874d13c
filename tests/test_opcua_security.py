"""OPC UA security against a server that requires encryption and rejects anonymous users."""

from __future__ import annotations

import asyncio
import shutil
import socket
from pathlib import Path

import pytest

from cnc_adapters.base import AdapterError, UnreachableError
from cnc_adapters.opcua import OpcUaAdapter
from cnc_adapters.sim import SpindlePlant, preset
from cnc_adapters.sim.vcnc import SimClock, VirtualCNC, VirtualMachine, running


def make_cert(directory: Path, name: str, uri: str, server: bool) -> tuple[str, str]:
    from asyncua.crypto.cert_gen import setup_self_signed_certificate
    from cryptography.x509.oid import ExtendedKeyUsageOID

    key, cert = directory / f"{name}-key.pem", directory / f"{name}-cert.der"
    use = [ExtendedKeyUsageOID.SERVER_AUTH if server else ExtendedKeyUsageOID.CLIENT_AUTH]
    asyncio.run(setup_self_signed_certificate(key, cert, uri, socket.gethostname(), use,
                                              {"commonName": name, "organizationName": "thermocomp tests"}))
    return str(cert), str(key)


@pytest.fixture(scope="module")
def pki(tmp_path_factory):
    d = tmp_path_factory.mktemp("pki")
    server = make_cert(d, "server", "urn:thermocomp:virtual-cnc:server", True)
    client = make_cert(d, "client", "urn:thermocomp:client", False)
    other = make_cert(d, "impostor", "urn:someone:else", True)
    trust = d / "trusted"
    trust.mkdir()
    shutil.copy(server[0], trust / "server.der")
    untrusted = d / "untrusted"
    untrusted.mkdir()
    shutil.copy(other[0], untrusted / "impostor.der")
    return {"server": server, "client": client, "trust": str(trust), "untrusted": str(untrusted), "dir": d}


@pytest.fixture
def secure_cnc(pki):
    vm = VirtualMachine(SpindlePlant(preset("motorized-27k")), None, clock=SimClock(60))
    vm.override_speed(15000.0)
    cnc = VirtualCNC(vm, certificate=pki["server"][0], private_key=pki["server"][1],
                     users={"operator": "s3cret-pw"})
    with running(cnc):
        yield cnc, vm


def secure_link(cnc, pki, mode="SignAndEncrypt", trust=None, **kw):
    return OpcUaAdapter(cnc.url, preset="virtual-cnc", security=f"Basic256Sha256,{mode}",
                        certificate=pki["client"][0], private_key=pki["client"][1],
                        trust_dir=trust or pki["trust"], timeout_s=5, **kw)


@pytest.mark.parametrize("mode", ["Sign", "SignAndEncrypt"])
def test_encrypted_session_with_user_from_the_environment(secure_cnc, pki, monkeypatch, mode):
    cnc, vm = secure_cnc
    monkeypatch.setenv("THERMOCOMP_OPCUA_USER", "operator")
    monkeypatch.setenv("THERMOCOMP_OPCUA_PASSWORD", "s3cret-pw")
    with secure_link(cnc, pki, mode) as link:
        assert link.read_speed() == 15000.0
        link.write_offset_um(-6.0)
    import time

    end = time.monotonic() + 10
    while vm.offset_um != -6.0 and time.monotonic() < end:
        time.sleep(0.02)
    assert vm.offset_um == -6.0


def test_password_from_a_file(secure_cnc, pki, monkeypatch, tmp_path):
    cnc, _ = secure_cnc
    monkeypatch.setenv("THERMOCOMP_OPCUA_USER", "operator")
    monkeypatch.delenv("THERMOCOMP_OPCUA_PASSWORD", raising=False)
    pw = tmp_path / "pw"
    pw.write_text("s3cret-pw\n")
    with secure_link(cnc, pki, password_file=str(pw)) as link:
        assert link.read_speed() == 15000.0


def test_anonymous_and_wrong_password_are_rejected(secure_cnc, pki, monkeypatch):
    cnc, _ = secure_cnc
    monkeypatch.delenv("THERMOCOMP_OPCUA_USER", raising=False)
    monkeypatch.delenv("THERMOCOMP_OPCUA_PASSWORD", raising=False)
    with pytest.raises(AdapterError, match="BadIdentityToken"):
        secure_link(cnc, pki).read_speed()
    monkeypatch.setenv("THERMOCOMP_OPCUA_USER", "operator")
    monkeypatch.setenv("THERMOCOMP_OPCUA_PASSWORD", "guess")
    with pytest.raises(AdapterError, match="Bad(UserAccessDenied|IdentityToken)"):
        secure_link(cnc, pki).read_speed()


def test_unencrypted_client_is_refused(secure_cnc, monkeypatch):
    cnc, _ = secure_cnc
    monkeypatch.setenv("THERMOCOMP_OPCUA_USER", "operator")
    monkeypatch.setenv("THERMOCOMP_OPCUA_PASSWORD", "s3cret-pw")
    with pytest.raises(UnreachableError, match="No matching endpoints"):
        OpcUaAdapter(cnc.url, preset="virtual-cnc", timeout_s=5).read_speed()


def test_server_outside_the_trust_list_is_refused(secure_cnc, pki, monkeypatch):
    cnc, _ = secure_cnc
    monkeypatch.setenv("THERMOCOMP_OPCUA_USER", "operator")
    monkeypatch.setenv("THERMOCOMP_OPCUA_PASSWORD", "s3cret-pw")
    with pytest.raises(UnreachableError, match="trust list"):
        secure_link(cnc, pki, trust=pki["untrusted"]).read_speed()


def test_secure_configuration_is_checked():
    with pytest.raises(AdapterError, match="trust_dir"):
        OpcUaAdapter("opc.tcp://127.0.0.1:1", preset="virtual-cnc", security="Basic256Sha256,SignAndEncrypt")
    with pytest.raises(AdapterError, match="security"):
        OpcUaAdapter("opc.tcp://127.0.0.1:1", preset="virtual-cnc", security="Basic128Rsa15,Sign",
                     certificate="c", private_key="k", trust_dir="t")
    with pytest.raises(TypeError):
        OpcUaAdapter("opc.tcp://127.0.0.1:1", preset="virtual-cnc", password="plain")  # type: ignore[call-arg]
