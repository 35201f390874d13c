"""OPC UA security against a server that requires encryption and rejects anonymous users."""

from __future__ import annotations

import asyncio
import logging
import shutil
import socket
import traceback
import uuid
from pathlib import Path

import pytest

from cnc_adapters.base import AdapterError, ConfigError, UnreachableError
from cnc_adapters.opcua import OpcUaAdapter
from machine_sim import SpindlePlant, preset
from machine_sim.vcnc import SimClock, VirtualCNC, VirtualMachine, running


def make_cert(directory: Path, name: str, uri: str, server: bool) -> tuple[str, str]:
    from asyncua.crypto.cert_gen import setup_self_signed_certificate
    from cryptography.x509.oid import ExtendedKeyUsageOID

    key, cert = directory / f"{name}-key.pem", directory / f"{name}-cert.der"
    use = [ExtendedKeyUsageOID.SERVER_AUTH if server else ExtendedKeyUsageOID.CLIENT_AUTH]
    asyncio.run(
        setup_self_signed_certificate(
            key,
            cert,
            uri,
            socket.gethostname(),
            use,
            {"commonName": name, "organizationName": "thermocomp tests"},
        )
    )
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
    return {
        "server": server,
        "client": client,
        "trust": str(trust),
        "untrusted": str(untrusted),
        "dir": d,
    }


@pytest.fixture
def secure_cnc(pki):
    vm = VirtualMachine(SpindlePlant(preset("motorized-27k")), None, clock=SimClock(60))
    vm.override_speed(15000.0)
    cnc = VirtualCNC(
        vm,
        certificate=pki["server"][0],
        private_key=pki["server"][1],
        users={"operator": "s3cret-pw"},
    )
    with running(cnc):
        yield cnc, vm


def secure_link(cnc, pki, mode="SignAndEncrypt", trust=None, **kw):
    return OpcUaAdapter(
        cnc.url,
        preset="virtual-cnc",
        security=f"Basic256Sha256,{mode}",
        certificate=pki["client"][0],
        private_key=pki["client"][1],
        trust_dir=trust or pki["trust"],
        timeout_s=5,
        **kw,
    )


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
        OpcUaAdapter(
            "opc.tcp://127.0.0.1:1", preset="virtual-cnc", security="Basic256Sha256,SignAndEncrypt"
        )
    with pytest.raises(AdapterError, match="security"):
        OpcUaAdapter(
            "opc.tcp://127.0.0.1:1",
            preset="virtual-cnc",
            security="Basic128Rsa15,Sign",
            certificate="c",
            private_key="k",
            trust_dir="t",
        )
    with pytest.raises(TypeError):
        OpcUaAdapter("opc.tcp://127.0.0.1:1", preset="virtual-cnc", password="plain")  # type: ignore[call-arg]


# -- secrets: systemd credentials, never a password in a URL, a message or a log line -------


def test_password_from_a_systemd_credential(secure_cnc, pki, monkeypatch, tmp_path, caplog):
    cnc, _ = secure_cnc
    secret = "s3cret-pw"
    monkeypatch.setenv("THERMOCOMP_OPCUA_USER", "operator")
    monkeypatch.delenv("THERMOCOMP_OPCUA_PASSWORD", raising=False)
    creds = tmp_path / "credentials"  # what systemd makes for LoadCredential=opcua-password:...
    creds.mkdir()
    (creds / "opcua-password").write_text(secret + "\n")
    monkeypatch.setenv("CREDENTIALS_DIRECTORY", str(creds))
    caplog.set_level(logging.DEBUG)  # every logger, asyncua's included
    with secure_link(cnc, pki, password_credential="opcua-password") as link:
        assert link.read_speed() == 15000.0
    (creds / "opcua-password").write_text("not-" + secret)
    with pytest.raises(AdapterError, match="Bad(UserAccessDenied|IdentityToken)") as info:
        secure_link(cnc, pki, password_credential="opcua-password").read_speed()
    assert secret not in caplog.text and secret not in chain(info.value)


def test_a_credential_without_systemd_is_one_clear_line(monkeypatch, tmp_path):
    monkeypatch.delenv("CREDENTIALS_DIRECTORY", raising=False)
    link = OpcUaAdapter(
        "opc.tcp://127.0.0.1:1", preset="virtual-cnc", password_credential="opcua-pw"
    )
    with pytest.raises(AdapterError) as info:
        link.read_speed()
    text = str(info.value)
    assert (
        "CREDENTIALS_DIRECTORY" in text and "LoadCredential=opcua-pw" in text and "\n" not in text
    )
    monkeypatch.setenv("CREDENTIALS_DIRECTORY", str(tmp_path))  # but no such credential in it
    link._next_attempt = float("-inf")  # past the back-off
    with pytest.raises(AdapterError, match="cannot read credential 'opcua-pw'"):
        link.read_speed()
    link.close()


def chain(err: BaseException) -> str:
    """An error as it would be logged: the whole traceback with its causes."""
    return "".join(traceback.format_exception(err))


@pytest.mark.parametrize("env", [None, "PLANT_OPCUA_PW"])
def test_a_url_with_a_password_is_refused_and_the_password_never_repeated(env, caplog, tmp_path):
    from cnc_adapters import check_adapter, open_adapter
    from cnc_adapters.sensors import open_sensor

    secret = f"pw-{uuid.uuid4().hex}"  # built here: no source line of a traceback holds it
    url = f"opc.tcp://operator:{secret}@127.0.0.1:4840/x"
    extra = {"password_env": env} if env else {}
    caplog.set_level(logging.DEBUG)
    attempts = [
        lambda: open_adapter(url + "?preset=virtual-cnc" + (f"&password_env={env}" if env else "")),
        lambda: open_adapter({"url": url, "preset": "virtual-cnc", **extra}),
        lambda: open_adapter({"type": "opcua", "url": url, "preset": "virtual-cnc", **extra}),
        lambda: check_adapter({"type": "opcua", "url": url, "preset": "virtual-cnc", **extra}),
        lambda: open_sensor({"url": url, "preset": "virtual-cnc", **extra}),
        lambda: open_sensor({"type": "opcua", "url": url, "preset": "virtual-cnc", **extra}),
        lambda: OpcUaAdapter(url, preset="virtual-cnc", **extra),
    ]
    for attempt in attempts:
        with pytest.raises((ConfigError, AdapterError)) as info:
            attempt()
        text = str(info.value)
        assert "\n" not in text and "password_file" in text and "LoadCredential=" in text
        assert (env or "THERMOCOMP_OPCUA_PASSWORD") in text
        assert secret not in chain(info.value)
    assert secret not in caplog.text


def test_user_information_in_a_url_is_redacted_from_messages():
    from cnc_adapters import open_adapter
    from machine_sim.vcnc import free_port

    secret = f"pw-{uuid.uuid4().hex}"  # built here: no source line of a traceback holds it
    for target in (f"ftp://someone:{secret}@host/x", f"sim://someone:{secret}@motorized-27k"):
        with pytest.raises(ConfigError) as info:
            open_adapter(target)
        assert secret not in chain(info.value)
    with pytest.raises(ConfigError) as info:
        open_adapter(
            {"type": "opcua", "url": f"http://someone:{secret}@host:1", "preset": "virtual-cnc"}
        )
    assert secret not in chain(info.value) and "***@host" in str(info.value)
    # a user name alone is allowed in the URL, but not repeated in messages either
    link = OpcUaAdapter(
        f"opc.tcp://someone@127.0.0.1:{free_port()}/x", preset="virtual-cnc", timeout_s=2
    )
    with pytest.raises(UnreachableError) as info:
        link.read_speed()
    assert "someone" not in str(info.value) and "://***@127.0.0.1" in str(info.value)
    link.close()
