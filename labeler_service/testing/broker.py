"""A throw-away Mosquitto on a free loopback port (tests, ``bench latency --transport mqtt``).

Not used by the service itself, which connects to whatever broker its settings name.
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import tempfile
import time
from pathlib import Path

from labeler_service.errors import ConfigError

#: The broker's largest packet (``max_packet_size``), as docker/mosquitto.conf ships it: a
#: larger publish is refused by the broker, not read whole by the service.
MAX_PACKET_BYTES = 1_048_576


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def mosquitto_binary() -> str | None:
    found = shutil.which("mosquitto")
    if found:
        return found
    for p in ("/usr/sbin/mosquitto", "/usr/local/sbin/mosquitto", "/opt/homebrew/sbin/mosquitto"):
        if Path(p).is_file():
            return p
    return None


class LocalBroker:
    """One Mosquitto process on ``127.0.0.1:port``; ``stop``/``start`` keep the port.

    ``users`` (name -> password) turns anonymous access off; ``tls`` = (CA, certificate, key)
    files makes the listener TLS-only.

    Use as a context manager or call ``start``/``stop``. Raises :class:`ConfigError` when the
    ``mosquitto`` binary is missing.
    """

    def __init__(
        self,
        workdir: Path | None = None,
        binary: str | None = None,
        users: dict[str, str] | None = None,
        tls: tuple[Path, Path, Path] | None = None,
    ) -> None:
        found = binary or mosquitto_binary()
        if found is None:
            raise ConfigError("the mosquitto binary was not found (apt install mosquitto)")
        self.binary: str = found
        self._tmp = None
        if workdir is None:
            self._tmp = tempfile.TemporaryDirectory(prefix="mocap-broker-")
            workdir = Path(self._tmp.name)
        self.host = "127.0.0.1"
        self.port = free_port()
        self.conf = Path(workdir) / "mosquitto.conf"
        auth = "allow_anonymous true\n"
        if users:
            auth = f"allow_anonymous false\npassword_file {self._password_file(workdir, users)}\n"
        if tls is not None:  # (cafile, certfile, keyfile): the listener speaks TLS only
            auth += f"cafile {tls[0]}\ncertfile {tls[1]}\nkeyfile {tls[2]}\n"
        # started as root, mosquitto drops to user "mosquitto", which cannot read our files
        stay = "user root\n" if hasattr(os, "geteuid") and os.geteuid() == 0 else ""
        self.conf.write_text(
            f"listener {self.port} 127.0.0.1\n{stay}{auth}persistence false\n"
            f"set_tcp_nodelay true\nmax_packet_size {MAX_PACKET_BYTES}\nlog_dest none\n"
        )
        self.proc: subprocess.Popen | None = None

    def _password_file(self, workdir: Path, users: dict[str, str]) -> Path:
        tool = shutil.which("mosquitto_passwd") or str(
            Path(self.binary).parent / "mosquitto_passwd"
        )
        path = Path(workdir) / "passwd"
        path.write_text("")
        for user, password in users.items():
            subprocess.run([tool, "-b", str(path), user, password], check=True,
                           capture_output=True)  # fmt: skip
        path.chmod(0o600)
        return path

    @property
    def url(self) -> str:
        return f"mqtt://{self.host}:{self.port}"

    def start(self, timeout: float = 10.0) -> None:
        self.proc = subprocess.Popen(
            [self.binary, "-c", str(self.conf)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise ConfigError(f"mosquitto exited with code {self.proc.returncode}")
            try:
                with socket.create_connection((self.host, self.port), timeout=0.2):
                    return
            except OSError:
                time.sleep(0.05)
        self.stop()
        raise ConfigError(f"mosquitto did not listen on port {self.port} within {timeout} s")

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=5)
        self.proc = None

    def close(self) -> None:
        self.stop()
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None

    def __enter__(self) -> LocalBroker:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
