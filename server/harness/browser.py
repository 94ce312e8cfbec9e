"""Debian's Chromium driven through Playwright, as the browser tests and the page benchmarks drive the pages.

Never downloads a browser: Chromium must be at ``CHROMIUM`` (``.ci/run`` installs Debian's ``chromium`` package).
Playwright is a test dependency, so it is imported where a browser starts, not with this module.
"""

from __future__ import annotations

import io
import tempfile
from collections.abc import Iterator, Sequence
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from PIL import Image

if TYPE_CHECKING:
    from playwright.sync_api import BrowserContext, Playwright

CHROMIUM = "/usr/bin/chromium"
#: The browser tests' flags: headless, no sandbox (containers), software rendering (SwiftShader), nothing fetched in
#: the background.
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--no-first-run", "--disable-sync", "--disable-quic"]
#: The page benchmarks' and screenshot scripts' flags (``benchmarks/bench_page.py`` measured with these).
BENCHMARK_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
                  "--disable-sync", "--no-first-run"]
VIEWPORT = {"width": 1280, "height": 720}


@contextmanager
def browser_session(profile: str | Path | None = None, *, playwright: Playwright | None = None,
                    args: Sequence[str] = CHROMIUM_ARGS, **options: Any) -> Iterator[BrowserContext]:
    """A fresh Chromium profile at 1280×720 with service workers blocked, as a browser test gets it.

    ``profile``: its folder (default: a temporary one, removed afterwards); ``playwright``: a running Playwright
    (default: one started for the session); ``options`` add to or replace Playwright's
    ``launch_persistent_context`` options (``viewport``, ``service_workers``, ...).
    """
    from playwright.sync_api import sync_playwright

    if not Path(CHROMIUM).exists():
        raise FileNotFoundError(f"{CHROMIUM} is missing: install Debian's chromium package (.ci/run does)")
    with ExitStack() as stack:
        if playwright is None:
            playwright = stack.enter_context(sync_playwright())
        if profile is None:
            profile = stack.enter_context(tempfile.TemporaryDirectory(prefix="trustlab-profile-"))
        context = playwright.chromium.launch_persistent_context(
            str(profile), executable_path=CHROMIUM, args=list(args), headless=True,
            **({"viewport": VIEWPORT, "service_workers": "block"} | options))
        try:
            yield context
        finally:
            context.close()


def red_share(png: bytes | np.ndarray) -> float:
    """Share of the pixels in the obstacles' red (experiment.world.scene.OBSTACLE_COLOR, however lit, and under
    viser's fade-in), not an item's orange or pink, the robot's orange nor the target's magenta."""
    rgb = png if isinstance(png, np.ndarray) else np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=float)
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    return float(np.mean((r > 90) & (r - g > 50) & (r - b > 50) & (np.abs(g - b) < 30)))
