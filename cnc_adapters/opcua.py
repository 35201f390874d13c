"""OPC UA controller link (asyncua, used through its synchronous wrapper).

Node ids come from configuration. ``{ns}`` in a node id is replaced by the index of
``namespace_uri`` on the server, so one configuration works whatever index the server gives
its namespace. Presets:

- ``virtual-cnc``: thermocomp's own virtual CNC (``machine_sim.vcnc``);
- ``sinumerik``: SINUMERIK Operate, speed ``/Channel/Spindle/actSpeed[u1,1]`` and the offset in
  an R parameter (``r_parameter`` selects which);
- ``opc40502``: OPC UA for CNC systems; ``ActSpeed`` of the ``CncSpindleType`` object named
  ``spindle`` is found by browse path; give the offset's ``offset_node`` or ``offset_path``;
- ``generic``: give ``speed_node``/``speed_path`` and ``offset_node``/``offset_path``
  (a browse path is ``0:Objects/2:Machine/2:Speed``, with ``{ns}`` for ``namespace_uri``).

The closed loop: ``measurement_node`` and ``measurement_sequence_node`` (optional
``measurement_sigma_node``) name the variables a probe or tool-setter cycle writes: the value
first, then a changed counter. Each value is used once; the counter found at connect is stale
(:meth:`~cnc_adapters.base.Adapter.read_measurement`). They are looked up at the first read,
so a wrong node is a failed measurement, never a failed link.

The cutting signal: ``cutting_node`` names a boolean (at speed and feeding, a cut in
progress) or an enumeration (a program or motion state); ``cutting_values`` are the values
that mean "cutting" (default ``[true]``; ``[false]`` for an inverted bit such as feed hold).
It is looked up at the first read: a wrong node is a failed cutting read (the runtime then
infers it from the speed), never a failed link.

One cycle, one request: :meth:`OpcUaAdapter.read` asks for every node the cycle wants in one
``Read`` (the speed, the cutting signal, the held offset, the inputs, the probe's handshake),
so all describe one instant; with a subscription the speed is its last notification and the
rest one request. Every value's status and type are checked where it enters: a value that is
not Good, or not a number where a number is due (a string, a boolean, an array, a byte string,
a date, null), is a :class:`~cnc_adapters.reading.Failure` of that value alone.
``verify_writes``: ``true``/``"immediate"`` reads the offset back after each write (a write
the controller did not take is refused); ``"deferred"`` checks it with the next cycle's read,
in the same request (:attr:`~cnc_adapters.reading.Reading.write_refused_um`); ``false`` never.
The per-value reads (``read_speed``, ``read_offset_um``, ...) ask the controller each time.

The sign of life: ``life_node`` (or ``life_path``) names the counter the control watches and
``valid_node`` (or ``valid_path``) the "compensation valid" flag; both, or neither (``""`` for
both turns a preset's off; the ``virtual-cnc`` preset names its ``LifeCounter`` and
``CompensationValid``). Each is written in its variable's own type (its DataType attribute is
read once a session): the counter as an integer or floating-point number, the flag as a
Boolean, or 1/0 in a number. They go in ONE ``Write`` request of their own, sent once the
offset's ``Write`` came back Good: a server takes each node of a request on its own, so a beat
in the offset's request would reach the control even with the offset refused. A life node that
does not exist, cannot hold the value or refuses the write leaves the offset taken: the write's
``life_failure`` names the node and how to turn the sign of life off (``life_node = ""``).

Security: ``security="Basic256Sha256,SignAndEncrypt"`` (or ``,Sign``) with a client
``certificate`` and ``private_key`` and a ``trust_dir`` of server certificates (DER or PEM);
a server whose certificate is not in the trust list is refused. The user name and password
come from the environment (``THERMOCOMP_OPCUA_USER``, ``THERMOCOMP_OPCUA_PASSWORD`` by
default), from a ``password_file``, or from a systemd credential (``password_credential =
"<name>"`` reads ``$CREDENTIALS_DIRECTORY/<name>``, which a unit's ``LoadCredential=`` provides),
never from the configuration itself: a URL with a password in it is refused, and URLs in log
lines and messages have their user information redacted.

A call that times out drops the session (a hung server, e.g. a stopped process, rarely answers
on the same session again) and raises :class:`AdapterTimeoutError`; the next call reconnects,
within ``timeout_s`` per request, connecting included.
"""

from __future__ import annotations

import concurrent.futures
import hashlib
import logging
import math
import os
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, ClassVar, Literal
from urllib.parse import urlsplit

from pydantic import AfterValidator, BaseModel, Field, model_validator

from .base import (
    _NOTHING_MORE,
    SETTINGS_CONFIG,
    Adapter,
    AdapterError,
    AdapterSettings,
    AdapterTimeoutError,
    Allowed,
    BadValueError,
    Count,
    CuttingValues,
    NonZero,
    Positive,
    RawMeasurement,
    Seconds,
    Text,
    UnreachableError,
    WriteRejectedError,
    _finite,
    _guarded,
    checked_life,
    cutting_of,
    life_configured,
    one_of,
    query_params,
    redact_url,
    short,
    url_has_password,
    whole_sequence,
)
from .reading import LIFE_MODULUS, Failure, Life, Reading, Wants

log = logging.getLogger("thermocomp.adapters.opcua")

PRESETS: dict[str, dict[str, Any]] = {
    "virtual-cnc": {
        "namespace_uri": "urn:thermocomp:virtual-cnc",
        "speed_node": "ns={ns};s=/CncInterface/CncSpindleList/Spindle1/ActSpeed",
        "offset_node": "ns={ns};s=/CncInterface/CncSpindleList/Spindle1/ThermalOffset",
        "input_nodes": {
            k: f"ns={{ns}};s=/CncInterface/CncSpindleList/Spindle1/Sensors/{v}"
            for k, v in (
                ("bearing_temp_c", "BearingTemp"),
                ("motor_temp_c", "MotorTemp"),
                ("coolant_temp_c", "CoolantTemp"),
                ("ambient_c", "AmbientTemp"),
                ("spindle_load_pct", "Load"),
            )
        },
        # its simulated tool setter
        "measurement_node": "ns={ns};s=/CncInterface/CncSpindleList/Spindle1/ToolSetter/Measurement",
        "measurement_sequence_node": "ns={ns};s=/CncInterface/CncSpindleList/Spindle1/ToolSetter/Sequence",
        "measurement_sigma_node": "ns={ns};s=/CncInterface/CncSpindleList/Spindle1/ToolSetter/Sigma",
        "cutting_node": "ns={ns};s=/CncInterface/CncSpindleList/Spindle1/Cutting",
        # the sign of life its watcher checks
        "life_node": "ns={ns};s=/CncInterface/CncSpindleList/Spindle1/LifeCounter",
        "valid_node": "ns={ns};s=/CncInterface/CncSpindleList/Spindle1/CompensationValid",
    },
    "sinumerik": {
        "speed_node": "ns=2;s=/Channel/Spindle/actSpeed[u1,1]",
        "offset_node": "ns=2;s=/Channel/Parameter/R[u1,{r}]",
        "offset_scale": 0.001,  # R parameters hold mm
    },
    # SINUMERIK with the offset in setting datum SD43900 (the sinumerik profile's OPC UA route):
    # its node id is configured (offset_node), as the server names it under /Sinumerik/SEA
    "sinumerik-sea": {
        "speed_node": "ns=2;s=/Channel/Spindle/actSpeed[u1,1]",
    },
    # OPC 40502 (OPC UA for CNC systems): the spindle found by browse path; the standard has
    # no thermal-offset variable, so offset_node or offset_path must name one
    "opc40502": {
        "namespace_uri": "http://opcfoundation.org/UA/CNC/",
        "speed_path": "0:Objects/{ns}:CncInterface/{ns}:CncSpindleList/{ns}:{spindle}/{ns}:ActSpeed",
    },
    "generic": {},
}


CREDENTIALS_ENV = "CREDENTIALS_DIRECTORY"
"""Where systemd puts a unit's ``LoadCredential=`` secrets, one file per credential name."""


def url_password_refusal(password_env: str = "THERMOCOMP_OPCUA_PASSWORD") -> str:
    """Why a URL with a password is refused, and where the password goes instead."""
    return (
        "the URL carries a password: refused (it would end up in logs); put it in "
        f'password_file, in a systemd credential (password_credential = "<name>" with '
        f"LoadCredential=<name>:<file> in the unit) or in the environment variable {password_env}"
    )


def quiet_asyncua_debug() -> None:
    """Hold asyncua's loggers at INFO: at DEBUG they repeat every request verbatim, the
    ActivateSession with the user's password in it included."""
    tree = [logging.getLogger("asyncua")]
    tree += [
        lg
        for name, lg in logging.root.manager.loggerDict.items()
        if name.startswith("asyncua.") and isinstance(lg, logging.Logger)
    ]
    quieted = False
    for lg in tree:
        if lg.getEffectiveLevel() < logging.INFO:
            lg.setLevel(logging.INFO)
            quieted = True
    if quieted:
        log.info("opcua: asyncua's debug log held at INFO while a password is in use")


def _opc_url(v: str) -> str:
    try:
        parts = urlsplit(v)
        parts.port  # noqa: B018 - raises on a port that is not a number
    except ValueError:
        raise ValueError("an opc.tcp://host:port URL") from None
    if parts.scheme != "opc.tcp" or not parts.hostname:
        raise ValueError("an opc.tcp://host:port URL")
    return v


def _security(v: str) -> str:
    if v != "None" and v not in ("Basic256Sha256,Sign", "Basic256Sha256,SignAndEncrypt"):
        raise ValueError("None, Basic256Sha256,Sign or Basic256Sha256,SignAndEncrypt")
    return v


OpcUrl = Annotated[str, AfterValidator(_opc_url), Allowed("an opc.tcp://host:port URL")]
Security = Annotated[
    str,
    AfterValidator(_security),
    Allowed("None, Basic256Sha256,Sign or Basic256Sha256,SignAndEncrypt"),
]
EnvName = Annotated[
    str,
    Field(pattern=r"^[A-Za-z_][A-Za-z0-9_]*$"),
    Allowed("an environment variable name (letters, digits, '_')"),
]


def _credential(v: str) -> str:
    if not v or len(v) > 255 or "/" in v or "\x00" in v or v in (".", ".."):
        raise ValueError("a systemd credential name (a file name: no '/')")
    return v


CredentialName = Annotated[
    str, AfterValidator(_credential), Allowed("a systemd credential name (a file name: no '/')")
]
VerifyWrites = Annotated[
    bool | Literal["immediate", "deferred"], Allowed("true, false, 'immediate' or 'deferred'")
]
if TYPE_CHECKING:  # a plain string to the type checker; pydantic checks the choice
    Preset = str
    ReadMode = str
else:
    Preset = one_of(*PRESETS)
    ReadMode = one_of("poll", "subscribe")


class OpcUaLinkSettings(BaseModel):
    """The options of an OPC UA session (adapter and sensor alike)."""

    model_config = SETTINGS_CONFIG

    url: OpcUrl = Field(description="opc.tcp://host:port/path; never with a password in it")
    namespace_uri: str | None = Field(None, description="its index replaces {ns} in node ids")
    timeout_s: Seconds = Field(4.0, description="per request, connecting included")
    security: Security = "None"
    certificate: str | None = Field(None, description="client certificate (secure links)")
    private_key: str | None = Field(None, description="client private key (secure links)")
    trust_dir: str | None = Field(None, description="server certificates to trust (secure links)")
    username_env: EnvName = "THERMOCOMP_OPCUA_USER"
    password_env: EnvName = "THERMOCOMP_OPCUA_PASSWORD"
    password_file: str | None = Field(None, description="a file holding the password")
    password_credential: CredentialName | None = Field(
        None, description="a systemd credential holding the password: $CREDENTIALS_DIRECTORY/<name>"
    )
    application_uri: Text = "urn:thermocomp:client"

    @model_validator(mode="after")
    def _session(self) -> OpcUaLinkSettings:
        if url_has_password(self.url):
            raise ValueError(url_password_refusal(self.password_env))
        if self.security != "None" and not (
            self.certificate and self.private_key and self.trust_dir
        ):
            raise ValueError(
                "a secure link (security other than None) needs certificate, "
                "private_key and trust_dir"
            )
        if self.password_file and self.password_credential:
            raise ValueError("give password_file or password_credential, not both")
        return self


class OpcUaSettings(OpcUaLinkSettings, AdapterSettings):
    """The options of :class:`OpcUaAdapter`."""

    preset: Preset = "generic"
    speed_node: str | None = Field(None, description="node id of the actual speed ({ns} allowed)")
    offset_node: str | None = Field(None, description="node id of the thermal offset")
    speed_path: str | None = Field(None, description="browse path of the actual speed")
    offset_path: str | None = Field(None, description="browse path of the thermal offset")
    spindle: Text = Field("Spindle1", description="opc40502: the CncSpindleType object's name")
    r_parameter: Count = Field(1, description="sinumerik: the R parameter holding the offset")
    verify_writes: VerifyWrites = True
    read_mode: ReadMode = "poll"
    publish_interval_ms: Positive = 50.0
    input_nodes: dict[str, str] | None = Field(
        None, description="extra channels: name = node id or browse path"
    )
    measurement_node: str | None = Field(
        None,
        description="closed loop: the tool length the probe cycle measured (node id or browse "
        "path), in the offset's unit, positive when the tool grew toward the workpiece",
    )
    measurement_sequence_node: str | None = Field(
        None, description="the counter the probe cycle changes after writing measurement_node"
    )
    measurement_sigma_node: str | None = Field(
        None, description="optional: the measurement's sigma, in the measurement's unit"
    )
    measurement_scale: NonZero = Field(  # type: ignore[assignment]
        None,
        description="controller unit per um of the measurement; default the offset's "
        "(1 for a probe cycle that hands over um while the offset is in mm)",
    )
    cutting_node: str | None = Field(
        None,
        description="the controller's cutting signal (node id or browse path): a boolean or "
        "an enumeration; '' for none, where a preset names one",
    )
    cutting_values: CuttingValues = Field(
        [True],  # type: ignore[arg-type]  # a list, as documented
        description="the values of cutting_node that mean cutting",
    )
    life_node: str | None = Field(
        None,
        description="the sign of life: the counter the control watches (node id; an integer "
        "or floating-point variable); '' for none, where a preset names one",
    )
    life_path: str | None = Field(None, description="the life counter by browse path")
    valid_node: str | None = Field(
        None,
        description="the sign of life: the 'compensation valid' flag (node id; a Boolean, or "
        "a number written 1/0); '' for none, where a preset names one",
    )
    valid_path: str | None = Field(None, description="the valid flag by browse path")

    @model_validator(mode="after")
    def _nodes(self) -> OpcUaSettings:
        p = PRESETS[self.preset]
        speed = self.speed_node or self.speed_path or p.get("speed_node") or p.get("speed_path")
        offset = (
            self.offset_node or self.offset_path or p.get("offset_node") or p.get("offset_path")
        )
        if not (speed and offset):
            raise ValueError(
                f"preset {self.preset!r} needs the speed and offset nodes: give "
                "speed_node or speed_path and offset_node or offset_path"
            )
        if bool(self.measurement_node) != bool(self.measurement_sequence_node) or (
            self.measurement_sigma_node and not self.measurement_node
        ):
            raise ValueError(
                "a measurement needs both measurement_node and measurement_sequence_node "
                "(the handshake), measurement_sigma_node only with them"
            )
        life_configured(
            life_ref(self.life_node, self.life_path, p.get("life_node")),
            life_ref(self.valid_node, self.valid_path, p.get("valid_node")),
            "life_node (or life_path)",
            "valid_node (or valid_path)",
        )
        return self


def life_ref(node: str | None, path: str | None, preset: str | None) -> str | None:
    """The configured reference of a sign-of-life variable: the node id or browse path given,
    else the preset's; ``""`` (given for either) turns the preset's off."""
    if node is None and path is None:
        return preset or None
    return node or path or None


class OpcUaLink:
    """Mixin for :class:`~cnc_adapters.base.Link` subclasses: an asyncua client session with
    optional security and credentials, shared by the adapter and the OPC UA sensor. Call
    :meth:`_init_opcua` from ``__init__``; implement :meth:`_on_connected` to look up nodes."""

    name: ClassVar[str]

    if TYPE_CHECKING:  # the Link's, which every class with this mixin derives from

        def _link_lost(
            self, message: str, error: type[AdapterError] = UnreachableError
        ) -> AdapterError: ...

    def _init_opcua(
        self,
        url: str,
        *,
        namespace_uri: str | None,
        timeout_s: float,
        security: str,
        certificate: str | None,
        private_key: str | None,
        trust_dir: str | None,
        username_env: str,
        password_env: str,
        password_file: str | None,
        application_uri: str,
        password_credential: str | None = None,
    ) -> None:
        if url_has_password(url):
            raise AdapterError(f"opcua: {url_password_refusal(password_env)}")
        if password_file and password_credential:
            raise AdapterError("opcua: give password_file or password_credential, not both")
        self.url = url
        self.shown_url = redact_url(url)  # the one that goes into messages
        self.namespace_uri = namespace_uri
        self.timeout_s = timeout_s
        self.security = security
        if security != "None":
            policy, _, mode = security.partition(",")
            if policy != "Basic256Sha256" or mode not in ("Sign", "SignAndEncrypt"):
                raise AdapterError(
                    f"opcua: security {security!r}: use None, Basic256Sha256,Sign "
                    "or Basic256Sha256,SignAndEncrypt"
                )
            if not (certificate and private_key and trust_dir):
                raise AdapterError(
                    "opcua: a secure link needs certificate, private_key and trust_dir"
                )
        self.certificate = certificate
        self.private_key = private_key
        self.trust_dir = trust_dir
        self.username_env = username_env
        self.password_env = password_env
        self.password_file = password_file
        self.password_credential = password_credential
        self.application_uri = application_uri
        self._client: Any = None  # an asyncua.sync.Client while open

    def _call(
        self, what: str, fn, *args, node: Any = None, refused: type[AdapterError] = AdapterError
    ):
        """Run one client call; map its failures onto the adapter exception tree, each message
        naming the operation, the node(s) (``node``: a node, a list of them, or the reference
        as configured) and the server: ``opcua read speed node ns=2;s=Speed at opc.tcp://...:
        BadNodeIdUnknown``. A timeout or a lost connection drops the session (the next call
        reconnects)."""
        from asyncua import ua
        from asyncua.sync import ThreadLoopNotRunning

        try:
            return fn(*args)
        except ua.UaStatusCodeError as err:
            raise refused(f"{self._where(what, node)}: {type(err).__name__}") from err
        except (TimeoutError, concurrent.futures.TimeoutError) as err:
            # a server that does not answer in time has most likely hung (a stopped process):
            # its session will not answer again, so drop it, but still say it was a timeout
            msg = f"{self._where(what, node)}: no answer within {self.timeout_s:g} s"
            if self._client is None:
                raise AdapterTimeoutError(msg) from err
            raise self._link_lost(msg, AdapterTimeoutError) from err
        except (ConnectionError, OSError, EOFError, ThreadLoopNotRunning) as err:
            msg = f"{self._where(what, node)}: {redact_url(str(err)) or type(err).__name__}"
            if self._client is None:
                raise UnreachableError(msg) from err
            raise self._link_lost(msg) from err

    def _where(self, what: str, node: Any = None) -> str:
        """``opcua <operation> <node(s)> at <server>``: the head of every message of a call."""
        nodes = node if isinstance(node, (list, tuple)) else [] if node is None else [node]
        shown = ", ".join(n if isinstance(n, str) else _node_id(n) for n in nodes)
        return f"opcua {what}{' ' + shown if shown else ''} at {self.shown_url}"

    def _credentials(self) -> tuple[str | None, str | None]:
        """The user name and password: a systemd credential, a password file or the environment.
        No message here ever holds the password."""
        user = os.environ.get(self.username_env)
        if self.password_credential:
            directory = os.environ.get(CREDENTIALS_ENV)
            if not directory:
                raise AdapterError(
                    f"opcua: password_credential {self.password_credential!r}: ${CREDENTIALS_ENV} "
                    f"is not set; systemd sets it for a unit with LoadCredential="
                    f"{self.password_credential}:<file>"
                )
            path, what = (
                Path(directory) / self.password_credential,
                f"credential {self.password_credential!r} in ${CREDENTIALS_ENV}",
            )
        elif self.password_file:
            path, what = Path(self.password_file), "password_file"
        else:
            return user, os.environ.get(self.password_env)
        try:
            return user, path.read_text(encoding="utf-8").rstrip("\r\n")
        except OSError as err:
            raise AdapterError(f"opcua: cannot read {what}: {err.strerror}") from err
        except UnicodeDecodeError as err:
            raise AdapterError(f"opcua: {what} is not UTF-8 text") from err

    def _trusted(self) -> set[str]:
        """SHA-256 fingerprints (DER) of the certificates in the trust list."""
        from cryptography import x509
        from cryptography.hazmat.primitives.serialization import Encoding

        prints = set()
        directory = Path(self.trust_dir or "")
        if not directory.is_dir():
            raise AdapterError(f"opcua: trust_dir {directory} is not a directory")
        for f in sorted(directory.iterdir()):
            data = f.read_bytes()
            try:
                cert = (
                    x509.load_pem_x509_certificate(data)
                    if b"-----BEGIN" in data
                    else x509.load_der_x509_certificate(data)
                )
            except ValueError:
                continue
            prints.add(hashlib.sha256(cert.public_bytes(Encoding.DER)).hexdigest())
        if not prints:
            raise AdapterError(f"opcua: no certificate in trust_dir {directory}")
        return prints

    def _secure(self, client) -> None:
        from asyncua import ua
        from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
        from cryptography.hazmat.primitives.serialization import Encoding

        trusted = self._trusted()

        async def validate(cert, _app) -> None:
            fp = hashlib.sha256(cert.public_bytes(Encoding.DER)).hexdigest()
            if fp not in trusted:
                raise ua.UaError(f"server certificate {fp[:16]}... is not in the trust list")

        client.aio_obj.certificate_validator = validate
        client.aio_obj.application_uri = self.application_uri
        mode = (
            ua.MessageSecurityMode.Sign
            if self.security.endswith(",Sign")
            else ua.MessageSecurityMode.SignAndEncrypt
        )
        self._call(
            "security",
            client.set_security,
            SecurityPolicyBasic256Sha256,
            self.certificate,
            self.private_key,
            None,
            None,
            mode,
        )

    def _connect(self) -> None:
        from asyncua import ua
        from asyncua.sync import Client

        # every request waits timeout_s at most (connecting: one per step, and a hung server
        # stalls only one); the wrapper's own limit is a backstop, not the normal way out
        client = Client(
            self.url, timeout=self.timeout_s, sync_wrapper_timeout=3 * self.timeout_s + 1
        )
        try:
            user, password = self._credentials()
            if user:
                client.set_user(user)
            if password:
                quiet_asyncua_debug()
                client.set_password(password)
            if self.security != "None":
                self._secure(client)
            self._call("connect", client.connect)
        except ua.UaError as err:
            self._client = client
            self._abort()
            raise UnreachableError(f"{self._where('connect')}: {redact_url(str(err))}") from err
        except AdapterError:
            self._client = client
            self._abort()  # also stops the client's own event-loop thread
            raise
        self._client = client
        try:
            ns = ""
            if self.namespace_uri:
                ns = str(
                    self._call(
                        "namespace lookup",
                        client.get_namespace_index,
                        self.namespace_uri,
                        node=self.namespace_uri,
                    )
                )
            self._on_connected(client, ns)
        except (AdapterError, ValueError) as err:
            self._abort()
            if isinstance(err, AdapterError):
                raise
            raise AdapterError(f"{self._where('resolve nodes')}: bad node id: {err}") from err

    def _on_connected(self, client: Any, ns: str) -> None:
        """Look up the nodes of this link (``ns``: the index of ``namespace_uri``)."""

    def _close_client(self, graceful: bool = True) -> None:
        client, self._client = self._client, None
        if client is None:
            return
        if graceful:
            try:
                client.disconnect()
            except Exception:  # noqa: BLE001 - a dead link cannot be closed more cleanly
                pass
            return
        aio = client.aio_obj

        async def drop() -> None:
            # a dead or hung session: no CloseSession round trip to wait a timeout for
            aio.disconnect_socket()
            try:
                await aio.close_session()  # stops asyncua's own tasks; the request fails at once
            except Exception:  # noqa: BLE001 - there is no socket any more: expected
                pass

        try:
            client.tloop.post(drop())
        except Exception:  # noqa: BLE001 - the client's loop may be gone already
            pass
        finally:
            if client.close_tloop:
                client.tloop.stop()

    def _forget(self) -> None:
        """Drop what belongs to one session (nodes, notifications); subclasses extend."""

    def _disconnect(self) -> None:
        self._forget()
        self._close_client()

    def _abort(self) -> None:
        self._forget()
        self._close_client(graceful=False)

    def _resolve(self, client, node_id: str | None, path: str | None, ns: str):
        if node_id:
            return client.get_node(node_id.replace("{ns}", ns))
        parts = path.replace("{ns}", ns).strip("/").split("/")  # type: ignore[union-attr]
        return self._call("browse", client.nodes.root.get_child, parts, node=path)

    def _resolve_ref(self, client, ref: str, ns: str, what: str):
        """A configured reference, a node id or a browse path (``0:Objects/...``), as a node; a
        reference that does not parse is an :class:`AdapterError` naming ``what``."""
        try:
            if ref.startswith("0:"):
                return self._resolve(client, None, ref, ns)
            return self._resolve(client, ref, None, ns)
        except AdapterError:
            raise
        except Exception as err:
            raise AdapterError(
                f"{self._where('resolve ' + what, ref)}: no node id or browse path "
                f"({type(err).__name__})"
            ) from err


class OpcUaAdapter(OpcUaLink, Adapter):
    name = "opcua"
    Settings = OpcUaSettings
    can_read_offset: ClassVar[bool] = True

    def __init__(
        self,
        url: str,
        *,
        preset: str = "generic",
        speed_node: str | None = None,
        offset_node: str | None = None,
        speed_path: str | None = None,
        offset_path: str | None = None,
        spindle: str = "Spindle1",
        namespace_uri: str | None = None,
        r_parameter: int = 1,
        timeout_s: float = 4.0,
        verify_writes: bool | str = True,
        security: str = "None",
        certificate: str | None = None,
        private_key: str | None = None,
        trust_dir: str | None = None,
        username_env: str = "THERMOCOMP_OPCUA_USER",
        password_env: str = "THERMOCOMP_OPCUA_PASSWORD",
        password_file: str | None = None,
        password_credential: str | None = None,
        application_uri: str = "urn:thermocomp:client",
        read_mode: str = "poll",
        publish_interval_ms: float = 50.0,
        input_nodes: dict[str, str] | None = None,
        measurement_node: str | None = None,
        measurement_sequence_node: str | None = None,
        measurement_sigma_node: str | None = None,
        measurement_scale: float | None = None,
        cutting_node: str | None = None,
        cutting_values: tuple[Any, ...] = (True,),
        life_node: str | None = None,
        life_path: str | None = None,
        valid_node: str | None = None,
        valid_path: str | None = None,
        **scaling: Any,
    ):
        if preset not in PRESETS:
            raise AdapterError(f"unknown OPC UA preset {preset!r}; known: {', '.join(PRESETS)}")
        p = dict(PRESETS[preset])
        for key in ("offset_scale", "offset_sign", "speed_scale"):
            if key in p and key not in scaling:
                scaling[key] = p[key]
        super().__init__(**scaling)
        self._init_opcua(
            url,
            namespace_uri=namespace_uri or p.get("namespace_uri"),
            timeout_s=timeout_s,
            security=security,
            certificate=certificate,
            private_key=private_key,
            trust_dir=trust_dir,
            username_env=username_env,
            password_env=password_env,
            password_file=password_file,
            application_uri=application_uri,
            password_credential=password_credential,
        )
        self.speed_node = speed_node or (None if speed_path else p.get("speed_node"))
        self.offset_node = offset_node or (None if offset_path else p.get("offset_node"))
        self.speed_path = None if self.speed_node else (speed_path or p.get("speed_path"))
        self.offset_path = None if self.offset_node else (offset_path or p.get("offset_path"))
        if self.speed_path:
            self.speed_path = self.speed_path.replace("{spindle}", spindle)
        if not (self.speed_node or self.speed_path) or not (self.offset_node or self.offset_path):
            raise AdapterError(
                "OPC UA adapter needs the speed and offset nodes (node id or browse "
                "path), or a preset that names them"
            )
        if self.offset_node:
            self.offset_node = self.offset_node.replace("{r}", str(r_parameter))
        # True/"immediate": read the offset back after each write (one more round trip);
        # "deferred": check it in the next read()'s request; False: never
        if verify_writes not in (True, False, "immediate", "deferred"):
            raise AdapterError("opcua: verify_writes is true, false, 'immediate' or 'deferred'")
        self.verify_writes = "immediate" if verify_writes is True else verify_writes
        self._unverified: float | None = None  # a write the next read() checks (deferred)
        if read_mode not in ("poll", "subscribe"):
            raise AdapterError("opcua: read_mode is 'poll' or 'subscribe'")
        self.read_mode = read_mode
        self.publish_interval_ms = publish_interval_ms
        self._latest: _Latest | None = None
        # extra channels (temperatures, load) by name: node ids ({ns} allowed) or browse paths
        self.input_nodes = dict(
            input_nodes if input_nodes is not None else p.get("input_nodes", {})
        )
        self._inputs: dict[str, Any] = {}
        self._speed: Any = None
        self._offset: Any = None
        # the probe cycle's handshake: (sequence, value[, sigma]), node ids or browse paths
        if measurement_node is None and measurement_sequence_node is None:
            measurement_node = p.get("measurement_node")
            measurement_sequence_node = p.get("measurement_sequence_node")
            measurement_sigma_node = measurement_sigma_node or p.get("measurement_sigma_node")
        if bool(measurement_node) != bool(measurement_sequence_node):
            raise AdapterError(
                "opcua: a measurement needs both measurement_node and measurement_sequence_node"
            )
        self.measurement_refs: tuple[str, ...] = (
            tuple(
                r
                for r in (measurement_sequence_node, measurement_node, measurement_sigma_node)
                if r
            )
            if measurement_node
            else ()
        )
        self.can_read_measurement = bool(self.measurement_refs)  # type: ignore[misc]
        self.measurement_scale = measurement_scale
        self._measurement: list[Any] | None = (
            None  # resolved lazily: a bad node never stops the link
        )
        # the cutting signal; "" turns a preset's off
        self.cutting_ref: str | None = (
            p.get("cutting_node") if cutting_node is None else (cutting_node or None)
        )
        self.can_read_cutting = bool(self.cutting_ref)  # type: ignore[misc]
        self.cutting_values = tuple(cutting_values)
        self._cutting_node: Any = None  # resolved at its first read
        # the sign of life: (counter, flag) references; "" turns a preset's off
        life = life_ref(life_node, life_path, p.get("life_node"))
        valid = life_ref(valid_node, valid_path, p.get("valid_node"))
        try:
            configured = life_configured(
                life, valid, "life_node (or life_path)", "valid_node (or valid_path)"
            )
        except ValueError as err:
            raise AdapterError(f"opcua: {err}") from None
        self.life_refs: tuple[str, str] | None = (
            (life, valid) if configured and life and valid else None
        )
        self.writes_life = self.life_refs is not None
        # resolved at the first write of a session: [(node, its VariantType)] counter, flag
        self._life: list[tuple[Any, Any]] | None = None
        self._ns = ""

    @classmethod
    def url_options(cls, url: str) -> dict[str, Any]:
        """``opc.tcp://host:4840/path?preset=virtual-cnc&timeout_s=2``."""
        return {"url": url.split("?", 1)[0], **query_params(url)}

    def _on_connected(self, client: Any, ns: str) -> None:
        self._ns = ns
        self._speed = self._resolve(client, self.speed_node, self.speed_path, ns)
        self._offset = self._resolve(client, self.offset_node, self.offset_path, ns)
        self._call("read speed node", self._speed.read_value, node=self._speed)
        self._inputs = {
            name: self._resolve_ref(client, ref, ns, f"input {name}")
            for name, ref in self.input_nodes.items()
        }
        if self._inputs:
            self._call(
                "read input nodes",
                client.read_values,
                list(self._inputs.values()),
                node=list(self._inputs.values()),
            )
        if self.read_mode == "subscribe":
            self._latest = _Latest(self._where("speed subscription", self._speed))
            sub = self._call(
                "subscribe", client.create_subscription, self.publish_interval_ms, self._latest
            )
            self._call(
                "subscribe to speed node", sub.subscribe_data_change, self._speed, node=self._speed
            )

    # -- one cycle: one request --------------------------------------------------

    def read(self, wants: Wants = _NOTHING_MORE) -> Reading:
        """This cycle's values in one ``Read`` request: the speed (polling; with a subscription,
        its last notification), and what ``wants`` asks for of the cutting signal, the held
        offset, the inputs and the probe's handshake, and the offset a deferred write check
        needs. Each value's status and type are checked and converted by the base's checks;
        a node that cannot be resolved fails its own field, never the cycle."""
        opened = _guarded(self.open)
        if isinstance(opened, Failure):
            return Reading(opened, reconnects=self.reconnects)
        speed: float | Failure | None = None
        if self._latest is not None:
            speed = _guarded(self._subscribed_speed)
            if isinstance(speed, Failure) and speed.link_lost:
                return Reading(speed, reconnects=self.reconnects)
        caps = self.capabilities
        fields: dict[str, Any] = {}
        request: dict[str, list[Any]] = {}  # the request's nodes, by field, in order
        if speed is None:
            request["speed"] = [self._speed]
        if self._unverified is not None or (wants.held_offset and caps.held_offset):
            request["offset"] = [self._offset]
        if wants.cutting and caps.cutting:
            node = _guarded(self._cutting_resolved)
            if isinstance(node, Failure):
                fields["cutting"] = node
            else:
                request["cutting"] = [node]
        if wants.inputs and caps.inputs:
            request["inputs"] = list(self._inputs.values())
        if wants.measurement and caps.measurement:
            nodes = _guarded(self._measurement_resolved)
            if isinstance(nodes, Failure):
                fields["measurement"] = nodes
            else:
                request["measurement"] = nodes
        lost = next((f for f in fields.values() if isinstance(f, Failure) and f.link_lost), None)
        if lost is not None or self._client is None:
            # the session dropped while a node was looked up: nothing more is asked this cycle
            lost = lost or Failure.of(UnreachableError(f"{self._where('read')}: session lost"))
            return Reading(
                speed if speed is not None else lost, reconnects=self.reconnects, **fields
            )
        nodes = [n for group in request.values() for n in group]
        dvs: Any = []
        if nodes:
            dvs = _guarded(
                lambda: self._call("read", self._client.read_attributes, nodes, node=nodes)
            )
            if not isinstance(dvs, Failure) and len(dvs) != len(nodes):
                dvs = Failure.of(
                    BadValueError(
                        f"{self._where('read')}: {len(dvs)} values for {len(nodes)} nodes"
                    )
                )
            if isinstance(dvs, Failure):  # the whole request: every value asked for fails
                for name in request:
                    fields["held_offset_um" if name == "offset" else name] = dvs
                if speed is None:
                    speed = fields.pop("speed")
                return Reading(speed, reconnects=self.reconnects, **fields)
        got: dict[str, list[Any]] = {}
        k = 0
        for name, group in request.items():
            got[name] = list(dvs[k : k + len(group)])
            k += len(group)
        if "speed" in got:
            speed = _guarded(lambda: self._speed_of(self._speed_raw_of(got["speed"][0])))
        assert speed is not None
        if "offset" in got:
            held = _guarded(lambda: self._offset_of(self._offset_raw_of(got["offset"][0])))
            if self._unverified is not None:
                fields["write_refused_um"] = self._check_deferred(got["offset"][0])
            if wants.held_offset and caps.held_offset:
                fields["held_offset_um"] = held
        if "cutting" in got:
            fields["cutting"] = _guarded(
                lambda: cutting_of(
                    self.name, self._cutting_raw_of(got["cutting"][0]), self.cutting_values
                )
            )
        if "inputs" in got:
            fields["inputs"] = _guarded(lambda: self._inputs_of(self._inputs_raw_of(got["inputs"])))
        if "measurement" in got:
            fields["measurement"] = _guarded(
                lambda: self._measurement_of(self._measurement_raw_of(got["measurement"]))
            )
        return Reading(speed, reconnects=self.reconnects, **fields)

    def _check_deferred(self, dv: Any) -> float | None:
        """The deferred check of the last write against the offset node's value read with this
        cycle: what the controller holds [um] when it did not take the write, else None."""
        wrote, self._unverified = self._unverified, None
        assert wrote is not None  # called only with a write to check
        held = _good_value(self._offset, dv, self._where("deferred write check", self._offset))
        if isinstance(held, BadValueError):  # not known: the next read-back checks it again
            log.warning("opcua: deferred write check: %s", held)
            return None
        number = _finite(held)
        if number is not None and math.isclose(number, wrote, rel_tol=1e-9, abs_tol=1e-9):
            return None
        log.warning("opcua: wrote %r, controller holds %s", wrote, short(held))
        if number is None:
            return None  # no number to report; the held offset's own read says what it holds
        um = self.units.to_um(number)
        return um if math.isfinite(um) else None

    def _write_pending(self) -> bool:
        return self._unverified is not None

    # -- the nodes' values: each status and type checked ------------------------

    def _checked(self, what: str, node: Any, dv: Any, error: type[AdapterError]) -> Any:
        """A DataValue's value; ``error`` naming the node and its status when it is not Good
        (a BadSensorFailure may carry a number: never taken)."""
        value = _good_value(node, dv, self._where(what, node))
        if isinstance(value, BadValueError):
            raise error(str(value))
        return value

    def _speed_raw_of(self, dv: Any) -> Any:
        value = self._checked("read speed node", self._speed, dv, AdapterError)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise BadValueError(
                f"{self._where('read speed node', self._speed)}: holds "
                f"{type(value).__name__}, not a number"
            )
        return value

    def _offset_raw_of(self, dv: Any) -> Any:
        return self._checked("read offset node", self._offset, dv, BadValueError)

    def _cutting_raw_of(self, dv: Any) -> Any:
        return self._checked("read cutting node", self._cutting_node, dv, AdapterError)

    def _inputs_raw_of(self, dvs: list[Any]) -> dict[str, Any]:
        # an input whose status is not Good is missing, as one that holds no number
        return {
            name: _good_value(node, dv, self._where("read input node", node))
            for (name, node), dv in zip(self._inputs.items(), dvs, strict=True)
        }

    def _measurement_raw_of(self, dvs: list[Any]) -> RawMeasurement:
        nodes = self._measurement or []
        seq, value, *sigma = (
            self._checked("read measurement node", node, dv, AdapterError)
            for node, dv in zip(nodes, dvs, strict=True)
        )
        if sigma and sigma[0] is None:  # a sigma node that holds nothing: refused, not "none"
            sigma = [_EMPTY]
        return RawMeasurement(whole_sequence(self.name, seq), value, sigma[0] if sigma else None)

    def _subscribed_speed(self) -> float:
        """The speed [rpm] from the subscription's last notification, checked."""
        return self._speed_of(self._subscribed_raw())

    def _subscribed_raw(self) -> float:
        """The subscription's last notification of the speed, a number (raw)."""
        assert self._latest is not None
        value = self._latest.get(self.timeout_s)
        if isinstance(value, BadValueError):
            raise value
        if isinstance(value, BaseException):
            raise self._link_lost(f"{self._where('speed subscription', self._speed)}: {value}")
        if value is None:
            raise self._link_lost(
                f"{self._where('speed subscription', self._speed)}: no "
                f"notification within {self.timeout_s:g} s",
                AdapterTimeoutError,
            )
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise BadValueError(
                f"{self._where('speed subscription', self._speed)}: holds "
                f"{type(value).__name__}, not a number"
            )
        return value

    def _cutting_resolved(self) -> Any:
        if self._cutting_node is None:
            assert self.cutting_ref is not None
            self._cutting_node = self._resolve_ref(
                self._client, self.cutting_ref, self._ns, "cutting node"
            )
        return self._cutting_node

    def _measurement_resolved(self) -> list[Any]:
        if self._measurement is None:
            self._measurement = [
                self._resolve_ref(self._client, ref, self._ns, "measurement node")
                for ref in self.measurement_refs
            ]
        return self._measurement

    def _read_one(self, what: str, nodes: list[Any]) -> list[Any]:
        """The DataValues of ``nodes``, in a request of their own."""
        return list(self._call(what, self._client.read_attributes, nodes, node=nodes))

    # -- the per-value reads (the wizard, run --check): each its own request ------

    def _read_speed_raw(self) -> Any:
        if self._latest is not None:
            return self._subscribed_raw()
        (dv,) = self._read_one("read speed node", [self._speed])
        return self._speed_raw_of(dv)

    def _read_cutting_raw(self) -> Any:
        node = self._cutting_resolved()
        (dv,) = self._read_one("read cutting node", [node])
        return self._cutting_raw_of(dv)

    def input_channels(self) -> tuple[str, ...]:
        return tuple(self.input_nodes)

    def _read_inputs_raw(self) -> dict[str, Any]:
        raw = self._inputs_raw_of(self._read_one("read input nodes", list(self._inputs.values())))
        return {
            name: (v if isinstance(v, (int, float)) and not isinstance(v, bool) else None)
            for name, v in raw.items()
        }

    def _read_offset_raw(self) -> Any:
        (dv,) = self._read_one("read offset node", [self._offset])
        return self._offset_raw_of(dv)

    def _read_measurement_raw(self) -> RawMeasurement:
        """The probe cycle's counter, value (and sigma), in one request, the counter first: the
        cycle writes the value before it changes the counter, so a new counter never comes with
        an old value."""
        nodes = self._measurement_resolved()
        return self._measurement_raw_of(self._read_one("read measurement nodes", nodes))

    def _write_offset_raw(self, value: float) -> None:
        from asyncua import ua

        dv = ua.DataValue(ua.Variant(float(value), ua.VariantType.Double))
        self._unverified = None
        try:
            self._call(
                "write offset node",
                self._offset.write_value,
                dv,
                node=self._offset,
                refused=WriteRejectedError,
            )
        except WriteRejectedError as err:
            raise self._offset_refused(err) from err
        self._offset_written(value)

    def _offset_refused(self, err: WriteRejectedError) -> WriteRejectedError:
        """A refused offset write, with the access right it needs where the server said so."""
        if "AccessDenied" not in str(err):
            return err
        return WriteRejectedError(
            f"{err}: the server's user may not write {self.offset_node or self.offset_path}; on a SINUMERIK, setting "
            "data need the SeaWrite right (GiveUserAccess, docs/controls/sinumerik.md)"
        )

    def _write_life_raw(self, life: Life) -> None:
        """The counter and the flag in ONE Write request (the offset's own Write came back Good
        before: a refused offset sends no beat), each result checked, naming its node."""
        life_values = self._life_values(life)  # converted and checked: nothing sent before
        nodes = [node for node, _ in self._life or []]
        what = "write sign of life"
        results = self._call(
            what,
            self._client.write_values,
            nodes,
            life_values,
            False,  # each result is checked below, by its node
            node=nodes,
            refused=WriteRejectedError,
        )
        if len(results) != len(nodes):
            raise BadValueError(
                f"{self._where(what, nodes)}: {len(results)} results for {len(nodes)} nodes"
            )
        for node, status, key in zip(nodes, results, ("life counter", "valid flag"), strict=True):
            if not status.is_good():
                option = "life_node" if key == "life counter" else "valid_node"
                raise WriteRejectedError(
                    f"{self._where('write ' + key + ' node', node)}: {status.name} (check "
                    f'{option}; {option} = "" turns the sign of life off)'
                )

    def _life_values(self, life: Life) -> list[Any]:
        """The counter and the flag as DataValues of their nodes' own types (the nodes looked
        up at the first write of a session); :class:`BadValueError` for a value the node's
        type cannot hold, before anything is sent."""
        from asyncua import ua

        life = checked_life(self.name, life)
        out = []
        for (node, vtype), value, key in zip(
            self._life_resolved(),
            (life.counter, life.valid),
            ("life counter", "valid flag"),
            strict=True,
        ):
            out.append(
                ua.DataValue(
                    ua.Variant(
                        _as_type(value, vtype, self._where("write " + key + " node", node)), vtype
                    )
                )
            )
        return out

    def _life_resolved(self) -> list[tuple[Any, Any]]:
        """The counter's and the flag's nodes and their VariantTypes, read in one request
        (their DataType attribute) at the first write of a session; :class:`AdapterError`
        naming each node that cannot be looked up."""
        if self._life is None:
            found, problems = self._life_lookup()
            if problems:
                raise AdapterError("; ".join(problems))
            self._life = found
        return self._life

    def _life_lookup(self) -> tuple[list[tuple[Any, Any]], list[str]]:
        """The sign of life's nodes and their VariantTypes (one Read of their DataType), and a
        line for each node that cannot be looked up, naming it and the option to change. A lost
        link is raised."""
        from asyncua import ua

        assert self.life_refs is not None  # writes_life
        keys = ("life counter", "valid flag")
        options = ("life_node", "valid_node")
        problems: list[str] = []

        def problem(option: str, text: str) -> None:
            problems.append(f'{text} (check {option}; {option} = "" turns the sign of life off)')

        nodes: list[Any] = []
        for ref, key, option in zip(self.life_refs, keys, options, strict=True):
            try:
                nodes.append(self._resolve_ref(self._client, ref, self._ns, key + " node"))
            except (UnreachableError, AdapterTimeoutError):
                raise
            except AdapterError as err:
                problem(option, str(err))
        if problems:
            return [], problems
        dvs = self._call(
            "read sign of life data types",
            self._client.read_attributes,
            nodes,
            ua.AttributeIds.DataType,
            node=nodes,
        )
        found = []
        for node, dv, key, option in zip(nodes, dvs, keys, options, strict=True):
            where = self._where(f"look up {key} node", node)
            if not dv.StatusCode.is_good():
                problem(option, f"{where}: {dv.StatusCode.name}")
                continue
            try:
                vtype = _variant_type(dv.Value.Value if dv.Value else None, where)
                # the counter runs to LIFE_MODULUS: a type that cannot hold it fails one day
                _as_type(LIFE_MODULUS if key == "life counter" else True, vtype, where)
            except AdapterError as err:
                problem(option, str(err))
                continue
            found.append((node, vtype))
        return found, problems

    def life_problems(self) -> list[str]:
        """The sign of life's nodes looked up, nothing written: one line per node that does not
        exist or whose type cannot hold the counter (up to 32767) or the flag."""
        if not self.writes_life:
            return []
        self.open()
        return self._life_lookup()[1]

    def _offset_written(self, value: float) -> None:
        """The offset's write was taken: its verification, as ``verify_writes`` says."""
        if self.verify_writes == "deferred":
            self._unverified = value
        elif self.verify_writes:
            (back_dv,) = self._read_one("read back offset node", [self._offset])
            back = self._checked("read back offset node", self._offset, back_dv, AdapterError)
            number = _finite(back)
            if number is None or not math.isclose(number, value, rel_tol=1e-9, abs_tol=1e-9):
                raise WriteRejectedError(
                    f"{self._where('write offset node', self._offset)}: wrote "
                    f"{value!r}, controller holds {short(back)}"
                )

    def _forget(self) -> None:
        self._latest = None
        self._unverified = None
        self._measurement = None
        self._cutting_node = None
        self._life = None


_NUMBER_TYPES = {
    "SByte": (-(2**7), 2**7 - 1),
    "Byte": (0, 2**8 - 1),
    "Int16": (-(2**15), 2**15 - 1),
    "UInt16": (0, 2**16 - 1),
    "Int32": (-(2**31), 2**31 - 1),
    "UInt32": (0, 2**32 - 1),
    "Int64": (-(2**63), 2**63 - 1),
    "UInt64": (0, 2**64 - 1),
}
_ABSTRACT = {26: "Double", 27: "Int32", 28: "UInt32"}  # Number, Integer, UInteger


def _variant_type(datatype: Any, where: str) -> Any:
    """The VariantType a variable of ``datatype`` (a NodeId of the standard namespace) takes:
    a Boolean, an integer or a floating-point type; :class:`AdapterError` for any other."""
    from asyncua import ua

    ident = getattr(datatype, "Identifier", None)
    ns = getattr(datatype, "NamespaceIndex", None)
    name = None
    if ns == 0 and isinstance(ident, int):
        name = _ABSTRACT.get(ident) or (ua.VariantType(ident).name if 1 <= ident <= 11 else None)
    if name is None:
        raise AdapterError(
            f"{where}: its data type {_node_id(datatype) if datatype is not None else None} "
            "is not a Boolean, an integer or a floating-point type"
        )
    return ua.VariantType[name]


def _as_type(value: int | bool, vtype: Any, where: str) -> Any:
    """A counter (int) or flag (bool) as a variable of ``vtype`` holds it: a Boolean takes a
    flag only; a number takes a flag as 1/0; an integer type must hold the counter."""
    name = vtype.name
    if name == "Boolean":
        if not isinstance(value, bool):
            raise BadValueError(f"{where}: a Boolean variable cannot hold the counter {value}")
        return value
    number = int(value)
    if name in ("Float", "Double"):
        return float(number)
    lo, hi = _NUMBER_TYPES[name]
    if not lo <= number <= hi:
        raise BadValueError(f"{where}: {number} does not fit its {name}")
    return number


class _Empty:
    """A node's value that is null (an empty variant), where a value is due."""

    def __repr__(self) -> str:
        return "null"


_EMPTY = _Empty()


def _node_id(node: Any) -> str:
    """A node's id as a user writes it (``ns=2;s=Speed``): a client's node, or a node id."""
    from asyncua import Node, ua
    from asyncua.sync import SyncNode

    if isinstance(node, (Node, SyncNode)):
        node = node.nodeid
    return node.to_string() if isinstance(node, ua.NodeId) else str(node)


def _good_value(node: Any, dv: Any, where: str) -> Any:
    """A DataValue's value if its status is Good, else a :class:`BadValueError` saying
    ``where`` (the operation, the node, the server) and the status."""
    if not dv.StatusCode.is_good():
        return BadValueError(f"{where}: status {dv.StatusCode.name}")
    return None if dv.Value is None else dv.Value.Value


class _Latest:
    """Subscription handler: keeps the last speed notification (or the link's failure); a
    notification whose status is not Good is kept as a :class:`BadValueError`."""

    def __init__(self, where: str) -> None:
        import threading

        self.where = where  # the operation, the node and the server, for every message
        self._value: Any = None
        self._event = threading.Event()

    def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
        # data: asyncua's DataChangeNotificationData; its DataValue carries the status
        self._value = _good_value(node, data.monitored_item.Value, self.where)
        self._event.set()

    def status_change_notification(self, status: Any) -> None:
        self._value = UnreachableError(f"{self.where}: subscription status {status}")
        self._event.set()

    def get(self, timeout_s: float) -> Any:
        self._event.wait(timeout_s)
        return self._value
