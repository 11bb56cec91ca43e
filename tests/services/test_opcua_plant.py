"""``twin plant-opcua`` is secured by default: Basic256Sha256 SignAndEncrypt only, user/password
sessions only, the bridge's per-run certificate the only client certificate trusted, and, as a
PLC exposes them, only the gate's command node writable; the ``BRIDGE.yaml`` it writes lets the
bridge connect. ``--insecure`` serves the open server and says so on stderr."""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from asyncua import Client, ua
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256

from schemas.bus_config import BusConfig
from schemas.opcua import BridgeConfig
from services.bus import free_port
from services.opcua_bridge import OpcuaBridge, wait_for

ROOT = Path(__file__).resolve().parents[2]
RECORDING = ROOT / "recordings" / "line1_30min.mcap"
TWIN = Path(sys.executable).with_name("twin")


class _Plant:
    """``twin plant-opcua`` as a user starts it, in its own folder; its stderr collected."""

    def __init__(self, cwd: Path, *args: str) -> None:
        self.port = free_port()
        self.err = cwd / "stderr.txt"
        self.proc = subprocess.Popen(
            [str(TWIN), "plant-opcua", str(RECORDING), "--port", str(self.port), *args],
            cwd=cwd,
            stdout=subprocess.PIPE,
            stderr=self.err.open("w"),
            text=True,
            env={**os.environ, "OPENBLAS_NUM_THREADS": "1"},
        )
        line = self.proc.stdout.readline()
        assert line.startswith("serving"), (line, self.err.read_text())
        self.endpoint = f"opc.tcp://127.0.0.1:{self.port}/twin/"

    def stop(self) -> int:
        self.proc.send_signal(signal.SIGINT)
        return self.proc.wait(30)


async def _session(endpoint: str, security: dict | None = None, user: str | None = None) -> str:
    """Connect (``security``: certificate, key and server certificate of a Basic256Sha256
    SignAndEncrypt session; ``user``: with the password from the config's file), then write a
    measurement node and the gate: what each gave."""
    client = Client(endpoint, timeout=10)
    if security is not None:
        await client.set_security(
            SecurityPolicyBasic256Sha256,
            security["certificate"],
            security["private_key"],
            server_certificate=security["server_certificate"],
            mode=ua.MessageSecurityMode.SignAndEncrypt,
        )
    if user is not None:
        client.set_user(user)
        client.set_password(Path(security["password_file"]).read_text())
    try:
        await client.connect()
    except Exception as exc:  # noqa: BLE001 - the refusal is the result
        return f"refused: {type(exc).__name__}"
    out = []
    try:
        for name, value in (("nir1.Concentration", 17.25), ("Gate.Command", '{"x": 1}')):
            node = client.get_node(f"ns=2;s={name}")
            kind = ua.VariantType.String if isinstance(value, str) else ua.VariantType.Double
            try:
                await node.write_value(ua.DataValue(ua.Variant(value, kind)))
                out.append(f"{name} written")
            except ua.UaStatusCodeError as exc:
                out.append(f"{name} {type(exc).__name__}")
    finally:
        await client.disconnect()
    return "; ".join(out)


def _own_certificate(folder: Path) -> dict[str, str]:
    """A client certificate the plant never saw (self-signed here)."""
    from asyncua.crypto.cert_gen import setup_self_signed_certificate
    from cryptography.x509.oid import ExtendedKeyUsageOID

    key, cert = folder / "stranger.pem", folder / "stranger.der"
    asyncio.run(
        setup_self_signed_certificate(
            key,
            cert,
            "urn:freeopcua:client",
            "localhost",
            [ExtendedKeyUsageOID.CLIENT_AUTH],
            {"commonName": "stranger"},
        )
    )
    return {"certificate": str(cert), "private_key": str(key)}


def test_the_default_plant_is_secured_and_exposes_only_the_gate(tmp_path):
    plant = _Plant(tmp_path, "--speed", "5", "--write-config", "bridge.yaml")
    try:
        # anonymous, security None: no endpoint for it
        assert asyncio.run(_session(plant.endpoint)).startswith("refused")
        err = plant.err.read_text()
        assert "security: Basic256Sha256 SignAndEncrypt, users twin" in err
        cfg = BridgeConfig.from_file(tmp_path / "bridge.yaml")
        sec = {k: str(v) for k, v in cfg.security.model_dump().items() if v is not None}
        assert sec["policy"] == "Basic256Sha256" and sec["mode"] == "SignAndEncrypt"
        assert (Path(sec["password_file"]).stat().st_mode & 0o777) == 0o600
        # signed and encrypted with a certificate of its own, anonymous or with the password
        stranger = {**sec, **_own_certificate(tmp_path)}
        assert asyncio.run(_session(plant.endpoint, stranger)).startswith("refused")
        assert asyncio.run(_session(plant.endpoint, stranger, "twin")).startswith("refused")
        # the bridge's certificate without a user: anonymous sessions are not offered
        assert asyncio.run(_session(plant.endpoint, sec)).startswith("refused")
        # the bridge's certificate and user: the gate only
        got = asyncio.run(_session(plant.endpoint, sec, "twin"))
        assert got.startswith("nir1.Concentration Bad") and got.endswith("Gate.Command written")
        # the bridge connects with the BRIDGE.yaml written for it and receives the plant's data
        bus = BusConfig(mode="peer", listen=[f"tcp/127.0.0.1:{free_port()}"], connect=[])
        with OpcuaBridge(cfg.model_copy(update={"diverter": None}), bus) as bridge:
            assert bridge.connected.wait(30)
            assert wait_for(lambda: bridge.counters.get("published") >= 3, 20)
    finally:
        assert plant.stop() == 0


def test_insecure_serves_the_open_server_and_says_so(tmp_path):
    plant = _Plant(tmp_path, "--insecure")
    try:
        time.sleep(0.2)
        err = plant.err.read_text()
        assert "warning: --insecure: security None, anonymous sessions" in err
        got = asyncio.run(_session(plant.endpoint))  # anonymous, no security: connects
        assert got.startswith("nir1.Concentration Bad") and got.endswith("Gate.Command written")
    finally:
        assert plant.stop() == 0
