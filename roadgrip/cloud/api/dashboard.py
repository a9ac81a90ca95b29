"""The live dashboard of `roadgrip serve`: one page that shows the friction map, the active warnings, every vehicle's
latest position, the roadside stations (their latest report: surface state, temperature, water film, friction, the mu
it gave and its age) and one chosen vehicle's mu with its 90 % interval over time. This module holds what the page is
served with (headers, config); its routes are in roadgrip/cloud/api/routes/dashboard.py.

| route | who | does |
| --- | --- | --- |
| GET /dashboard | anyone | the page (static/index.html); it holds no data |
| GET /dashboard/config.json | anyone | what the page needs to draw, no secrets: tile URL, H3 resolution, refresh period |
| GET /dashboard/static/... | anyone | the page's script and style, and Leaflet 1.9.4 (vendored: no internet needed) |
| GET /v1/vehicles/latest | admin, reader | each vehicle's newest estimate (CONTRACTS 3.4) with its position |

Data. The page is a reader like any other: it calls /v1/map, /v1/warnings, /v1/vehicles/latest, /v1/stations and
/v1/vehicles/{id}/estimates with HTTP Basic credentials. It takes them from the URL fragment
(`/dashboard#operator:SECRET`: a browser never sends the fragment to the server, nor in a Referer) or from its login
form, keeps them in the tab's sessionStorage and removes the fragment from the address bar.

Live by polling, every REFRESH_INTERVAL_S, not by a websocket: each view is a snapshot the server computes on request
anyway (the map at this instant, the active warnings), so polling needs no connection state or fan-out in the service,
authenticates every request the same way as any API call, passes proxies and load balancers that do not upgrade
connections, and recovers from a restart by itself. At 1 s it costs five small requests a second per open page, the
chart's only asking for the estimates newer than those it has. A push channel pays off for sub-second latency or many
viewers, neither of which a control-room page has.

Base map: tiles only from `Settings.map_tiles_url` (for example https://tile.openstreetmap.org/{z}/{x}/{y}.png, whose
usage policy asks for light use and its attribution); without it the page draws the cells on a plain background and
makes no request outside this server. The page's Content-Security-Policy admits images from the tile server's origin
and nothing else from outside.

Test hook: when the page has drawn, its root element (#dashboard) carries data-status ("ok", "login", "unauthorized",
"forbidden", "error", "unreachable"), data-cells, data-cells-measured, data-warnings, data-vehicles, data-stations, data-chart-vehicle,
data-chart-points and data-updated (ms since the epoch, browser clock), which `chromium --headless --dump-dom` shows.
"""

from __future__ import annotations

import html
from pathlib import Path
from urllib.parse import urlsplit

from roadgrip.cloud.settings import Settings

STATIC_DIR = Path(__file__).parent / "static"
REFRESH_INTERVAL_S = 1.0  # the page's polling period
CHART_WINDOW_S = 300.0  # the chart shows the chosen vehicle's last 5 min of estimates (3,000 at 10 Hz)
OSM_ATTRIBUTION = '&copy; <a href="https://www.openstreetmap.org/copyright">OpenStreetMap</a> contributors'


def tile_source(tiles_url: str | None) -> str | None:
    """The CSP source that admits the tiles of `tiles_url`: its origin, a `{s}` subdomain as `*`; None for no tiles
    or tiles from this server; the scheme alone where the host is a template CSP cannot express."""
    if tiles_url is None or tiles_url.startswith("/"):
        return None
    parts = urlsplit(tiles_url)
    host = parts.netloc
    if host.startswith("{s}."):
        host = "*." + host[len("{s}.") :]
    if "{" in host or "}" in host:
        return f"{parts.scheme}:"
    return f"{parts.scheme}://{host}"


def tile_attribution(tiles_url: str | None) -> str | None:
    """The attribution to show under the tiles: OpenStreetMap's for its servers, else the tile server's host."""
    if tiles_url is None:
        return None
    host = urlsplit(tiles_url).netloc.lower()
    if host == "openstreetmap.org" or host.endswith(".openstreetmap.org"):
        return OSM_ATTRIBUTION
    return f"tiles: {html.escape(host)}" if host else None


def content_security_policy(tiles_url: str | None) -> str:
    """Scripts, styles and data from this server only; images also from the tile server; no framing, no form
    submission (the login form is handled by the script, so that a secret never ends up in a URL)."""
    images = " ".join(s for s in ("'self'", "data:", tile_source(tiles_url)) if s)  # data: Leaflet's blank tile
    # 'unsafe-inline' styles: Leaflet writes style attributes in markup (its popups: Leaflet issue #9168)
    return (
        "default-src 'none'; script-src 'self'; style-src 'self' 'unsafe-inline'; "
        f"img-src {images}; connect-src 'self'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'"
    )


def page_headers(settings: Settings) -> dict[str, str]:
    """The headers of the page: its Content-Security-Policy, no MIME sniffing, revalidated on every load."""
    return {
        "Content-Security-Policy": content_security_policy(settings.map_tiles_url),
        "X-Content-Type-Options": "nosniff",
        "Cache-Control": "no-cache",
    }


def page_config(settings: Settings) -> dict:
    """GET /dashboard/config.json: what the page needs to draw, no secrets."""
    return {
        "map_tiles_url": settings.map_tiles_url,
        "map_tiles_attribution": tile_attribution(settings.map_tiles_url),
        "h3_resolution": settings.h3_resolution,
        "refresh_interval_s": REFRESH_INTERVAL_S,
        "chart_window_s": CHART_WINDOW_S,
        "warning_threshold_mu": settings.warning_threshold_mu,
    }
