"""The viewer: public pages under a same-origin CSP, their static files, and the page in a browser.

The fast tests call the app in process (no weights, no lifespan). The browser test drives headless
Chromium (Debian packages ``chromium`` and ``chromium-driver``) against a live server that wants
an API key: it uploads a view of proc-0001 through the page, waits for the answer, and checks the
page's text, the pixels of its 3D view (observed and model colours), that the key typed into the
page was sent, and that no request left the server's origin. With ``CATALIGN_WRITE_DOCS=1`` it
also saves the screenshot as ``docs/viewer.png``; otherwise it writes nothing into the repository.
"""

from __future__ import annotations

import asyncio
import base64
import hashlib
import io
import json
import os
import re
import shutil
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import httpx
import numpy as np
import pytest

from catalign.api.app import create_app
from catalign.api.settings import ServiceSettings

if TYPE_CHECKING:
    from tests.api.conftest import Server, View

ROOT = Path(__file__).resolve().parents[2]
STATIC = ROOT / "service/catalign/api/static"
DOCS_PNG = ROOT / "docs/viewer.png"
API_KEY = "viewer-test-key-0123"
PAGES = ("/", "/viewer")
# The page's colours (viewer.js COLORS) as RGB.
BACKGROUND = (250, 250, 250)
OBSERVED = (0x1F, 0x5F, 0xA8)
MODEL = (0xE8, 0x73, 0x0C)

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CHROMEDRIVER = shutil.which("chromedriver")
CHROME_ARGS = (
    "--headless=new",
    "--no-sandbox",  # the tests run as root
    "--disable-gpu",
    "--enable-unsafe-swiftshader",  # WebGL on the CPU: newer Chromium no longer falls back alone
    "--window-size=1400,850",
    "--force-device-scale-factor=1",
)


def get(*paths: str, api_key: str | None = API_KEY) -> list[httpx.Response]:
    """GET each path from an in-process app (no lifespan: pages and files need no model)."""
    app = create_app(ServiceSettings(api_key=api_key))

    async def ask() -> list[httpx.Response]:
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://viewer.test") as http:
            return [await http.get(path) for path in paths]

    return asyncio.run(ask())


def import_map(html: str) -> str:
    found = re.search(r'<script type="importmap">(.*?)</script>', html, re.DOTALL)
    assert found is not None
    return found.group(1)


def test_pages_are_public_html_under_a_same_origin_policy() -> None:
    *pages, guarded = get(*PAGES, "/models")
    assert guarded.status_code == 401  # the key still guards the data
    for page in pages:
        assert page.status_code == 200
        assert page.headers["content-type"].startswith("text/html")
        policy = page.headers["content-security-policy"]
        assert "default-src 'self'" in policy and "connect-src 'self'" in policy
        assert "unsafe-inline" not in policy and "unsafe-eval" not in policy
        assert not re.search(r"https?:|\*|data:|blob:", policy)
    viewer_page = pages[1].text
    digest = hashlib.sha256(import_map(viewer_page).encode()).digest()
    assert (
        f"'sha256-{base64.b64encode(digest).decode()}'"
        in pages[1].headers["content-security-policy"]
    )
    assert not re.search(r"""(src|href)=["']?(https?:)?//""", viewer_page)


def test_the_index_links_to_the_viewer_the_docs_and_readiness() -> None:
    (index,) = get("/")
    for target in ("/viewer", "/docs", "/health/ready"):
        assert f'href="{target}"' in index.text


def test_the_pages_stay_out_of_the_openapi_schema() -> None:
    paths = create_app(ServiceSettings()).openapi()["paths"]
    assert not set(PAGES) & set(paths)
    assert not [p for p in paths if p.startswith("/viewer")]


def test_every_module_the_page_imports_is_served_from_the_origin() -> None:
    """Follow the page's scripts, its import map and each module's imports: all answer 200."""
    (page,) = get("/viewer", api_key=None)
    imports: dict[str, str] = json.loads(import_map(page.text))["imports"]
    pending = re.findall(r'(?:src|href)="(/viewer/static/[^"]+)"', page.text)
    seen: dict[str, httpx.Response] = {}
    while pending:
        path = pending.pop()
        if path in seen:
            continue
        (seen[path],) = get(path, api_key=None)
        assert seen[path].status_code == 200, path
        assert seen[path].headers["x-content-type-options"] == "nosniff"
        if path.endswith(".js"):
            assert "javascript" in seen[path].headers["content-type"]
            specifiers = re.findall(r"""(?:from|import)\s*['"]([^'"]+)['"]""", seen[path].text)
            pending += [_resolve(s, path, imports) for s in specifiers]
    served = {p.rsplit("/", 1)[-1] for p in seen}
    assert {
        "viewer.js",
        "formats.js",
        "three.module.js",
        "three.core.js",
        "OrbitControls.js",
    } <= served


def _resolve(specifier: str, importer: str, imports: dict[str, str]) -> str:
    """A module specifier as the browser resolves it: import map first, then relative."""
    if specifier in imports:
        return imports[specifier]
    for prefix, target in imports.items():
        if prefix.endswith("/") and specifier.startswith(prefix):
            return target + specifier[len(prefix) :]
    assert specifier.startswith("./"), f"{importer} imports {specifier} from outside"
    return importer.rsplit("/", 1)[0] + specifier[1:]


def test_the_vendored_three_js_matches_its_version_file() -> None:
    vendor = STATIC / "vendor/three"
    revision = re.search(r"REVISION = '(\d+)'", (vendor / "three.core.js").read_text())
    assert revision is not None
    assert (vendor / "VERSION").read_text().strip() == f"0.{revision.group(1)}.0"
    assert "MIT License" in (vendor / "LICENSE").read_text()


# --- the page in a real browser ------------------------------------------------------------------


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    if CHROMIUM is None or CHROMEDRIVER is None:
        pytest.skip(
            "headless Chromium is not installed: the Debian packages chromium and "
            "chromium-driver are needed (scripts/setup.sh installs them)"
        )
    webdriver = pytest.importorskip("selenium.webdriver", reason="selenium (dev extra) is needed")
    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for argument in CHROME_ARGS:
        options.add_argument(argument)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(
        options=options, service=webdriver.ChromeService(executable_path=CHROMEDRIVER)
    )
    try:
        yield driver
    finally:
        driver.quit()


@pytest.fixture(scope="module")
def server(browser: Any, serve: Callable, library_dir: Path) -> Iterator[Server]:
    """A live server that wants an API key (started once the browser is known to work)."""
    with serve(library=library_dir, api_key=API_KEY, warmup=False, deadline_s=120) as running:
        yield running


@pytest.mark.slow
def test_the_viewer_registers_a_scan_and_draws_the_answer(
    browser: Any, server: Server, views: Callable[..., View], tmp_path: Path
) -> None:
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys

    scan = tmp_path / "scan.npy"
    np.save(scan, views(1).points)
    browser.get(f"{server.url}/viewer")
    wait_for(browser, "return document.body.dataset.state === 'ready'", 30, "the page's module")
    browser.find_element(By.ID, "file").send_keys(str(scan))
    key = browser.find_element(By.ID, "api-key")
    key.send_keys("not-the-key")
    browser.find_element(By.ID, "register").click()
    wait_for(browser, _error_says("wrong API key"), 30, "the server's 401 message")

    key.send_keys(Keys.CONTROL, "a")
    key.send_keys(API_KEY)
    browser.find_element(By.ID, "register").click()
    wait_for(browser, "return document.body.dataset.state === 'answered'", 120, "the answer")
    wait_for(browser, "return document.querySelectorAll('#models li').length === 3", 30, "library")

    text = {name: browser.find_element(By.ID, name).text for name in _ANSWER_FIELDS}
    assert text["model-id"] == "proc-0001" and text["answer-category"] == "chair"
    assert text["answer-symmetry"] == "no turn"  # proc-0001 looks different turned
    assert float(text["fitness"]) > 0.5
    assert "total" in text["timings"] and len(text["candidates"].splitlines()) == 3
    assert not browser.find_element(By.ID, "error").is_displayed()

    png = screenshot(browser)
    pixels = canvas_pixels(browser, png)
    assert share_unlike(pixels, BACKGROUND) > 0.01, "the 3D view is blank"
    assert share_like(pixels, OBSERVED) > 0.001, "no observed points drawn"
    assert share_like(pixels, MODEL) > 0.001, "no model points drawn"
    if os.environ.get("CATALIGN_WRITE_DOCS") == "1":
        DOCS_PNG.write_bytes(png)

    browser.find_element(By.CSS_SELECTOR, "#models button[data-model-id='proc-0002']").click()
    wait_for(browser, _status_starts("proc-0002"), 30, "the library model")
    alone = canvas_pixels(browser, screenshot(browser))
    assert share_like(alone, MODEL) > 0.001 and share_like(alone, OBSERVED) == 0

    urls = browser.execute_script(
        "return [location.href, "
        "...performance.getEntriesByType('resource').map((entry) => entry.name)]"
    )
    assert len(urls) > 5 and all(u.startswith(f"{server.url}/") for u in urls), urls
    assert "X-API-Key" not in browser.current_url and API_KEY not in browser.current_url
    assert browser.execute_script("return localStorage.length + sessionStorage.length") == 0
    assert browser.execute_script("return document.cookie") == ""
    violations = [e for e in browser.get_log("browser") if "Content Security" in e["message"]]
    assert not violations

    browser.find_element(By.ID, "category").send_keys("sofa")
    browser.find_element(By.ID, "register").click()
    wait_for(browser, _error_says("no model of category 'sofa'"), 60, "the unknown category")


_ANSWER_FIELDS = (
    "model-id",
    "answer-category",
    "answer-symmetry",
    "fitness",
    "inlier-rmse",
    "timings",
    "candidates",
)


@pytest.mark.slow
def test_the_page_draws_every_cloud_format_it_reads(
    browser: Any, server: Server, views: Callable[..., View], tmp_path: Path
) -> None:
    """Each file is parsed in the browser: its point count and extent show in the status line."""
    from selenium.webdriver.common.by import By

    points = views(2, step=4).points
    extent = points.max(axis=0) - points.min(axis=0)
    browser.get(f"{server.url}/viewer")
    wait_for(browser, "return document.body.dataset.state === 'ready'", 30, "the page's module")
    for path in cloud_files(points, tmp_path):
        browser.find_element(By.ID, "file").send_keys(str(path))
        wait_for(browser, _status_starts(f"{len(points)} points read"), 30, path.name)
        status = browser.find_element(By.ID, "status").text
        sizes = [float(v) for v in re.findall(r"\d+\.\d+", status)]
        np.testing.assert_allclose(sizes, extent, atol=0.011, err_msg=path.name)

    # A variant the page does not read (binary_compressed .pcd) is still registered: model only.
    compressed = tmp_path / "compressed.pcd"
    write_cloud(compressed, points, compressed=True)
    browser.find_element(By.ID, "file").send_keys(str(compressed))
    wait_for(browser, _status_starts("cannot draw this file"), 30, "the status")
    browser.find_element(By.ID, "api-key").send_keys(API_KEY)
    browser.find_element(By.ID, "register").click()
    wait_for(browser, "return document.body.dataset.state === 'answered'", 120, "the answer")
    drawn = canvas_pixels(browser, screenshot(browser))
    assert share_like(drawn, MODEL) > 0.001 and share_like(drawn, OBSERVED) == 0


def cloud_files(points: np.ndarray, folder: Path) -> list[Path]:
    """The same cloud as .npy (float32, float64, Fortran order), .xyz, ASCII/binary .ply/.pcd."""
    arrays = {
        "f4.npy": points,
        "f8.npy": points.astype("<f8"),
        "fortran.npy": np.asfortranarray(points.astype("<f8")),
    }
    for name, array in arrays.items():
        np.save(folder / name, array)
    np.savetxt(folder / "cloud.xyz", points, fmt="%.6f")
    clouds = ["ascii.ply", "binary.ply", "ascii.pcd", "binary.pcd"]
    for name in clouds:
        write_cloud(folder / name, points, write_ascii=name.startswith("ascii"))
    return [*(folder / n for n in [*arrays, "cloud.xyz", *clouds])]


def write_cloud(path: Path, points: np.ndarray, **options: bool) -> None:
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    assert o3d.io.write_point_cloud(str(path), cloud, **options)


def _error_says(words: str) -> str:
    return f"return document.getElementById('error').textContent.includes({json.dumps(words)})"


def _status_starts(words: str) -> str:
    return f"return document.getElementById('status').textContent.startsWith({json.dumps(words)})"


def wait_for(browser: Any, script: str, timeout: float, what: str) -> None:
    """Wait until ``script`` returns something true; on timeout, fail with the browser's log."""
    from selenium.common.exceptions import TimeoutException
    from selenium.webdriver.support.ui import WebDriverWait

    try:
        WebDriverWait(browser, timeout, poll_frequency=0.2).until(
            lambda driver: driver.execute_script(script)
        )
    except TimeoutException:
        log = "\n".join(e["message"] for e in browser.get_log("browser"))
        error = browser.execute_script("return document.getElementById('error').textContent")
        pytest.fail(f"waited {timeout:.0f} s for {what or script}; page error: {error!r}\n{log}")


def screenshot(browser: Any) -> bytes:
    """A PNG of the window once the next two frames were drawn."""
    browser.execute_async_script("requestAnimationFrame(() => requestAnimationFrame(arguments[0]))")
    return browser.get_screenshot_as_png()


def canvas_pixels(browser: Any, png: bytes) -> np.ndarray:
    """RGB pixels of the 3D view in ``png``, the legend painted over with the background."""
    from PIL import Image

    image = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).copy()
    rects = browser.execute_script(
        "return ['#canvas', '.legend'].map((s) => {"
        "  const r = document.querySelector(s).getBoundingClientRect();"
        "  return [r.left, r.top, r.right, r.bottom].map((v) => v * devicePixelRatio); })"
    )
    (left, top, right, bottom), legend = (np.round(r).astype(int) for r in np.array(rects))
    image[legend[1] : legend[3], legend[0] : legend[2]] = BACKGROUND
    return image[top:bottom, left:right]


def share_unlike(pixels: np.ndarray, color: tuple[int, int, int], tolerance: int = 24) -> float:
    distance = np.abs(pixels.astype(int) - color).max(axis=-1)
    return float((distance > tolerance).mean())


def share_like(pixels: np.ndarray, color: tuple[int, int, int], tolerance: int = 24) -> float:
    return 1.0 - share_unlike(pixels, color, tolerance)
