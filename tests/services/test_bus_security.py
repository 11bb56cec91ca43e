"""Bus security on loopback: TLS, mutual TLS, user/password authentication and access control
(only the diverter may publish divert commands), all from BusConfig (zenoh's own transport
security, exercised with a throwaway test CA made by the openssl CLI)."""

from __future__ import annotations

import shutil
import subprocess
import time
from pathlib import Path

import pytest
import zenoh

from schemas.bus_config import AccessControl, BusConfig, Tls, UserPassword
from services.bus import free_port, open_session
from services.security import write_private

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl CLI")

NAMES = ("router", "diverter", "rogue", "recorder")
DIVERT = "twin/l1/divert/command"
FLOW = "twin/l1/feeder/api/flow"


def _openssl(*args: str, cwd: Path) -> None:
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True)


def _make_ca(d: Path, ca: str, names: tuple[str, ...]) -> None:
    d.mkdir(parents=True, exist_ok=True)
    ec = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes"]
    _openssl(
        "req",
        "-x509",
        *ec,
        "-keyout",
        f"{ca}.key",
        "-out",
        f"{ca}.pem",
        "-days",
        "2",
        "-subj",
        f"/CN={ca}",
        cwd=d,
    )
    ext = d / "leaf.ext"
    ext.write_text(
        "subjectAltName=DNS:localhost,IP:127.0.0.1\nbasicConstraints=CA:FALSE\n"
        "keyUsage=digitalSignature,keyEncipherment\nextendedKeyUsage=serverAuth,clientAuth\n"
    )
    for n in names:
        _openssl("req", *ec, "-keyout", f"{n}.key", "-out", f"{n}.csr", "-subj", f"/CN={n}", cwd=d)
        _openssl(
            "x509",
            "-req",
            "-in",
            f"{n}.csr",
            "-CA",
            f"{ca}.pem",
            "-CAkey",
            f"{ca}.key",
            "-CAcreateserial",
            "-out",
            f"{n}.pem",
            "-days",
            "2",
            "-extfile",
            "leaf.ext",
            cwd=d,
        )


@pytest.fixture(scope="module")
def pki(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("pki")
    _make_ca(d, "ca", NAMES)
    _make_ca(d / "other", "otherca", ("intruder",))
    return d


def listen_tls(d: Path, mtls: bool) -> Tls:
    return Tls(
        root_ca_certificate=d / "ca.pem",
        listen_certificate=d / "router.pem",
        listen_private_key=d / "router.key",
        enable_mtls=mtls,
    )


def connect_tls(d: Path, name: str | None, ca: Path | None = None) -> Tls:
    if name is None:
        return Tls(root_ca_certificate=ca or d / "ca.pem")
    cert_dir = d if (d / f"{name}.pem").exists() else d / "other"
    return Tls(
        root_ca_certificate=ca or d / "ca.pem",
        connect_certificate=cert_dir / f"{name}.pem",
        connect_private_key=cert_dir / f"{name}.key",
        enable_mtls=True,
    )


def divert_acl(subject_field: str) -> AccessControl:
    """Default deny; everyone may subscribe and publish feeder data; divert commands are
    delivered to everyone but accepted (ingress) only from the diverter."""
    everyone = {"id": "everyone", subject_field: ["diverter", "rogue", "recorder"]}
    diverter = {"id": "diverter", subject_field: ["diverter"]}
    return AccessControl.model_validate(
        {
            "default_permission": "deny",
            "rules": [
                {
                    "id": "subscribe",
                    "permission": "allow",
                    "key_exprs": ["twin/**"],
                    "messages": [
                        "declare_subscriber",
                        "liveliness_token",
                        "declare_liveliness_subscriber",
                        "liveliness_query",
                    ],
                },
                {
                    "id": "data",
                    "permission": "allow",
                    "key_exprs": ["twin/*/feeder/**"],
                    "messages": ["put"],
                },
                {
                    "id": "divert_out",
                    "permission": "allow",
                    "key_exprs": ["twin/*/divert/command"],
                    "messages": ["put"],
                    "flows": ["egress"],
                },
                {
                    "id": "divert_in",
                    "permission": "allow",
                    "key_exprs": ["twin/*/divert/command"],
                    "messages": ["put"],
                    "flows": ["ingress"],
                },
            ],
            "subjects": [everyone, diverter],
            "policies": [
                {"rules": ["subscribe", "data", "divert_out"], "subjects": ["everyone"]},
                {"rules": ["divert_in"], "subjects": ["diverter"]},
            ],
        }
    )


def exchange(hub_cfg: BusConfig, client_cfgs: dict[str, BusConfig]) -> list[tuple[str, bytes]]:
    """Open the hub and the clients; 'recorder' subscribes to twin/**; 'rogue' publishes a divert
    command and a flow, 'diverter' a divert command; returns what the recorder received."""
    got: list[tuple[str, bytes]] = []
    with open_session(hub_cfg):
        sessions = {n: open_session(c) for n, c in client_cfgs.items()}
        try:
            sessions["recorder"].declare_subscriber(
                "twin/**", lambda s: got.append((str(s.key_expr), s.payload.to_bytes()))
            )
            time.sleep(0.5)
            sessions["rogue"].put(DIVERT, b"rogue")
            sessions["rogue"].put(FLOW, b"rogue")
            sessions["diverter"].put(DIVERT, b"diverter")
            deadline = time.monotonic() + 5
            while time.monotonic() < deadline and (DIVERT, b"diverter") not in got:
                time.sleep(0.05)
            time.sleep(0.3)
        finally:
            for s in sessions.values():
                s.close()
    return got


def test_tls_link_delivers_and_rejects_untrusted_server(pki):
    ep = f"tls/localhost:{free_port()}"
    hub = BusConfig(mode="router", listen=[ep], connect=[], tls=listen_tls(pki, mtls=False))
    clients = {
        n: BusConfig(mode="client", connect=[ep], tls=connect_tls(pki, None))
        for n in ("diverter", "rogue", "recorder")
    }
    got = exchange(hub, clients)
    assert sorted(got) == sorted([(DIVERT, b"rogue"), (FLOW, b"rogue"), (DIVERT, b"diverter")])
    # a client trusting another CA cannot connect (client mode fails at once)
    with open_session(hub):
        bad = BusConfig(
            mode="client",
            connect=[ep],
            tls=connect_tls(pki, None, ca=pki / "other" / "otherca.pem"),
        )
        with pytest.raises(zenoh.ZError):
            open_session(bad).close()
    # a plain-TCP client cannot talk to a TLS listener
    with open_session(hub):
        with pytest.raises(zenoh.ZError):
            open_session(BusConfig(mode="client", connect=[ep.replace("tls/", "tcp/")])).close()


def test_mtls_requires_a_client_certificate_from_the_ca(pki):
    ep = f"tls/localhost:{free_port()}"
    hub = BusConfig(mode="router", listen=[ep], connect=[], tls=listen_tls(pki, mtls=True))
    with open_session(hub):
        with open_session(BusConfig(mode="client", connect=[ep], tls=connect_tls(pki, "recorder"))):
            pass
        with pytest.raises(zenoh.ZError):
            open_session(BusConfig(mode="client", connect=[ep], tls=connect_tls(pki, None))).close()
        with pytest.raises(zenoh.ZError):
            open_session(
                BusConfig(mode="client", connect=[ep], tls=connect_tls(pki, "intruder"))
            ).close()


def test_acl_by_certificate_only_diverter_publishes_divert_commands(pki):
    ep = f"tls/localhost:{free_port()}"
    hub = BusConfig(
        mode="router",
        listen=[ep],
        connect=[],
        tls=listen_tls(pki, mtls=True),
        access_control=divert_acl("cert_common_names"),
    )
    clients = {
        n: BusConfig(mode="client", connect=[ep], tls=connect_tls(pki, n))
        for n in ("diverter", "rogue", "recorder")
    }
    got = exchange(hub, clients)
    assert (DIVERT, b"diverter") in got
    assert (FLOW, b"rogue") in got
    assert (DIVERT, b"rogue") not in got


def test_user_password_auth_and_acl_by_username(tmp_path, monkeypatch):
    users = tmp_path / "users.txt"
    users.write_text("diverter:pw-d\nrogue:pw-r\nrecorder:pw-c\n")
    ep = f"tcp/127.0.0.1:{free_port()}"
    hub = BusConfig(
        mode="router",
        listen=[ep],
        connect=[],
        usrpwd=UserPassword(dictionary_file=users),
        access_control=divert_acl("usernames"),
    )

    def client(user: str, pw: str) -> BusConfig:
        """A client whose password comes from a 0600 file (never inline)."""
        path = tmp_path / f"{user}-{pw}.pw"
        write_private(path, pw)
        up = UserPassword(user=user, password_file=path)
        return BusConfig(mode="client", connect=[ep], usrpwd=up)

    passwords = {"diverter": "pw-d", "rogue": "pw-r", "recorder": "pw-c"}
    got = exchange(hub, {n: client(n, pw) for n, pw in passwords.items()})
    assert (DIVERT, b"diverter") in got
    assert (FLOW, b"rogue") in got
    assert (DIVERT, b"rogue") not in got
    with open_session(hub):
        with pytest.raises(zenoh.ZError):
            open_session(client("rogue", "wrong")).close()
        with pytest.raises(zenoh.ZError):
            open_session(BusConfig(mode="client", connect=[ep])).close()
        # the password from an environment variable works as from a file
        monkeypatch.setenv("TEST_TWIN_PW", "pw-c")
        env = UserPassword(user="recorder", password_env="TEST_TWIN_PW")
        open_session(BusConfig(mode="client", connect=[ep], usrpwd=env)).close()


def test_passwords_are_never_inline_and_their_files_private(tmp_path):
    """A configuration with an inline password is refused; a password file readable by others,
    an unset variable and a listener beyond loopback without TLS or authentication are refused
    when the session opens, each naming the field."""
    with pytest.raises(ValueError, match="password must not be written in a configuration"):
        BusConfig.model_validate({"usrpwd": {"user": "u", "password": "secret"}})
    loose = tmp_path / "pw"
    loose.write_text("secret")
    loose.chmod(0o644)
    cfg = BusConfig(usrpwd=UserPassword(user="u", password_file=loose))
    with pytest.raises(ValueError, match="password_file must be readable by its owner only"):
        open_session(cfg)
    cfg = BusConfig(usrpwd=UserPassword(user="u", password_env="TWIN_TEST_UNSET_VARIABLE"))
    with pytest.raises(ValueError, match="password_env names an unset environment variable"):
        open_session(cfg)
    exposed = BusConfig(mode="router", listen=["tcp/0.0.0.0:7447"], connect=[])
    assert exposed.insecure_listeners() == ["tcp/0.0.0.0:7447"]
    with pytest.raises(ValueError, match="bus.listen: tcp/0.0.0.0:7447"):
        open_session(exposed)
    assert BusConfig(mode="router", listen=["tcp/127.0.0.1:7447"]).insecure_listeners() == []
    assert BusConfig(listen=["tls/0.0.0.0:7447"]).insecure_listeners() == []
    auth = UserPassword(dictionary_file=tmp_path / "users")
    assert BusConfig(listen=["tcp/10.0.0.1:7447"], usrpwd=auth).insecure_listeners() == []
