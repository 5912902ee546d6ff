"""The viser server every h2viz page is served by (dashboard, replay, HTML export): local-only, quiet, themed."""

from __future__ import annotations

import base64
import contextlib
import io
import logging
from importlib import resources

import viser
from viser.theme import TitlebarConfig, TitlebarImage

log = logging.getLogger("h2viz.viewer")


class LocalViserServer(viser.ViserServer):
    """A ViserServer that never opens a share tunnel (no outbound connections), even on request."""

    def request_share_url(self, verbose: bool = True) -> str | None:
        log.warning("share links are disabled in h2viz; the dashboard stays on this machine")
        return None


LOGO = resources.files("h2viz") / "assets" / "logo.svg"
"""The dashboard's logo, shipped with h2viz (assets/logo.svg in a clone)."""


def logo() -> TitlebarImage:
    """The logo as an inline image for the title bar (no request back to the server)."""
    data = base64.b64encode(LOGO.read_bytes()).decode()
    url = f"data:image/svg+xml;base64,{data}"
    return TitlebarImage(image_url_light=url, image_url_dark=url, image_alt="h2viz", href=None)


def make_viser_server(host: str, port: int, label: str = "h2viz") -> LocalViserServer:
    """Start a quiet, local-only viser server (dark theme, no share button)."""
    with contextlib.redirect_stdout(io.StringIO()):  # viser announces itself on stdout
        server = LocalViserServer(host=host, port=port, label=label, verbose=False)
    server.gui.configure_theme(
        titlebar_content=TitlebarConfig(buttons=None, image=logo()),
        dark_mode=True,
        show_share_button=False,
        show_logo=False,
        brand_color=(40, 150, 255),
        control_width="large",
    )
    # Plain lights, no environment map: its prefiltering stalls software-rendered browsers for seconds.
    server.scene.configure_environment_map(None)
    server.scene.configure_default_lights(cast_shadow=False)
    server.scene.add_light_hemisphere("/lights/sky", sky_color=(255, 255, 255), ground_color=(110, 110, 120))
    return server
