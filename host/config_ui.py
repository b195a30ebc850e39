"""`[ui]`: the operator station the daemon serves (host/station): where it listens, who may use it.

The station has the same two roles as the TCP control listener: an operator token grants motion,
a viewer token grants the view and the status (and STOP / E-STOP, as everywhere). Empty tokens
never match, so a station without tokens serves only its static page.
"""

from __future__ import annotations

from dataclasses import dataclass

from host.config_fields import spec

MIN_TOKEN_CHARS = 16  # host.config.MIN_TOKEN_CHARS: guessing a token through hello is hopeless

LOOPBACK_HOSTS = ("127.0.0.1", "::1", "localhost")


@dataclass(frozen=True)
class UiConfig:
    """The operator station: the live AR view and the touch controls in a browser."""

    enabled: bool = spec(False, doc="serve the operator station")
    host: str = spec("127.0.0.1", doc="listen address (0.0.0.0 for a touch screen on the LAN)")
    port: int = spec(8080, lo=0, hi=65535, doc="listen port (0: any free port)")
    operator_token: str = spec("", doc="token granting motion from the page")
    viewer_token: str = spec("", doc="token granting the view and the status only")
    tls_cert: str = spec("", doc="TLS certificate file (PEM); empty: plain HTTP")
    tls_key: str = spec("", doc="TLS private key file (PEM), with tls_cert")
    jpeg_quality: int = spec(80, lo=10, hi=100, doc="JPEG quality of the live view")
    ghost: bool = spec(True, doc="also draw the encoder-only registration, before drift correction")
    status_hz: float = spec(5.0, lo=0.2, hi=30.0, doc="rate of status pushes to each page")
    deadman_ms: float = spec(
        250.0, lo=50.0, hi=2000.0, doc="a jog stops when the page's hold messages pause this long"
    )
    parts_path: str = spec(
        "", doc="workpiece parts and feature points (JSON); empty: beside the model file"
    )


def ui_problems(ui: UiConfig) -> list[str]:
    """Rules spanning several `[ui]` keys, as `key: reason` lines."""
    problems = []
    if ui.enabled and not (ui.operator_token or ui.viewer_token):
        problems.append("ui.operator_token: a token (operator or viewer) is required when enabled")
    if bool(ui.tls_cert) != bool(ui.tls_key):
        problems.append("ui.tls_key: tls_cert and tls_key are given together or not at all")
    for key in ("operator_token", "viewer_token"):
        if 0 < (n := len(getattr(ui, key))) < MIN_TOKEN_CHARS:
            problems.append(f"ui.{key}: {n} characters, need {MIN_TOKEN_CHARS} or more")
    if ui.operator_token and ui.operator_token == ui.viewer_token:
        problems.append("ui.viewer_token: must differ from ui.operator_token")
    return problems
