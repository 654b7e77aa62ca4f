"""The Sphinx site (``make docs``): it builds with no warning, documents every name of every
package's ``__all__`` (and of its public modules' where the package does not export them), and
no internal link of a built page is broken.

The site is built once per test run (``python -m sphinx -W -n`` into a temporary folder, about
20 s on one core); under pytest-xdist the first worker to ask builds it and the others read
it. This folder is collected first, so that the build starts as the run does.
"""

from __future__ import annotations

import importlib
import importlib.util
import json
import os
import re
import subprocess
import sys
import zlib
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import unquote, urlsplit

import pytest
from filelock import FileLock

pytest.importorskip(
    "sphinx", reason="the docs' dependencies are not installed (pip install -e '.[docs]')"
)

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"
# The packages of the API reference (docs/conf.py's API_PACKAGES): each exports its public names.
PACKAGES = (
    "envs",
    "data",
    "collectors",
    "modules",
    "estimators",
    "objectives",
    "fitting",
    "trainers",
    "planners",
    "transforms",
    "policies",
    "evaluation",
    "experiments",
    "reports",
    "errors",
)
# A package's names that another package exports too (docs/conf.py's API_REEXPORTS): documented
# under the other, their home.
REEXPORTS = {"modules": "estimators"}
# The modules whose public names their package does not export (docs/conf.py's API_MODULES).
MODULES = ("trainers.configs",) + tuple(
    f"planners.{module}"
    for module in ("base", "sampling", "cem", "elite_memory", "noise", "registry", "bounds")
    + ("beta", "planning_model", "executors", "cpu_threads", "torchrl_models", "model_env")
)


def build(out: Path) -> dict:
    """Build the site into ``out/html``; return the return code and the warnings.

    With Sphinx's ``basic`` theme, not the site's furo: the same sources, extensions, pages and
    links, but furo spends over half of a build (~30 of ~55 s here) writing every page's whole
    navigation tree, and it checks nothing of its own."""
    cmd = [sys.executable, "-m", "sphinx", "-W", "--keep-going", "-n", "-q", "-b", "html"]
    cmd += ["-D", "html_theme=basic"]
    cmd += ["-d", str(out / "doctrees"), str(DOCS), str(out / "html")]
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=900)
    warnings = [
        line
        for line in done.stderr.splitlines()
        if re.search(r"\b(WARNING|ERROR|CRITICAL)\b", line)
    ]
    return {"returncode": done.returncode, "warnings": warnings, "stderr": done.stderr[-4000:]}


@pytest.fixture(scope="session")
def site(tmp_path_factory) -> tuple[Path, dict]:
    """The built site's folder and the build's outcome (built once across xdist workers)."""
    shared = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):  # this run's folder, common to its workers
        shared = shared.parent
    shared = shared / "docs_site"
    shared.mkdir(exist_ok=True)
    with FileLock(str(shared) + ".lock"):
        record = shared / "build.json"
        if not record.exists():
            record.write_text(json.dumps(build(shared)))
    return shared / "html", json.loads(record.read_text())


@pytest.mark.slow  # the Sphinx build (39 s); `make docs` builds it too
def test_builds_without_warnings(site):
    _, outcome = site
    assert outcome["warnings"] == [], "\n".join(outcome["warnings"])
    assert outcome["returncode"] == 0, outcome["stderr"]


def inventory(html: Path) -> dict[str, tuple[str, str]]:
    """``objects.inv``: ``name -> (domain:role, page uri)``."""
    raw = (html / "objects.inv").read_bytes()
    header_end = 0
    for _ in range(4):  # "# Sphinx inventory version 2", project, version, "zlib" line
        header_end = raw.index(b"\n", header_end) + 1
    entries = {}
    for line in zlib.decompress(raw[header_end:]).decode().splitlines():
        found = re.match(r"(.+?)\s+(\S+:\S+)\s+(-?\d+)\s+(\S*)\s+(.*)", line.rstrip())
        if found:
            name, role, _, uri, _ = found.groups()
            entries[name] = (role, uri.replace("$", name) if uri.endswith("$") else uri)
    return entries


@pytest.mark.slow  # the Sphinx build (39 s); `make docs` builds it too
def test_every_public_name_has_an_api_page(site):
    html, outcome = site
    assert (html / "objects.inv").exists(), outcome["stderr"]
    entries = inventory(html)
    missing, empty = [], []
    exported = set()
    for package in PACKAGES:
        module = importlib.import_module(f"torchrl_recon.{package}")
        exported |= {id(getattr(module, name)) for name in module.__all__}
    for package in PACKAGES + MODULES:
        module = importlib.import_module(f"torchrl_recon.{package}")
        home = importlib.import_module(f"torchrl_recon.{REEXPORTS.get(package, package)}")
        at_home = {id(getattr(home, name)) for name in home.__all__} if home is not module else ()
        for name in module.__all__:
            full = f"{module.__name__}.{name}"
            if package in MODULES and id(getattr(module, name)) in exported:
                continue  # documented under its package
            if id(getattr(module, name)) in at_home:
                continue  # documented under its home package
            if full not in entries or not entries[full][0].startswith("py:"):
                missing.append(full)
                continue
            page = html / urlsplit(entries[full][1]).path
            text = page.read_text() if page.exists() else ""
            if f'id="{full}"' not in text:
                empty.append(full)
    assert not missing, f"public names without an API entry: {missing}"
    assert not empty, f"API entries whose page lacks the object's description: {empty}"


@pytest.mark.slow  # the Sphinx build (39 s); `make docs` builds it too
def test_api_pages_show_signature_docstring_and_example(site):
    html, _ = site
    page = (html / "api/generated/torchrl_recon.planners.CEMPlanner.html").read_text()
    assert 'class="sig sig-object py"' in page and "num_candidates" in page
    assert "Examples" in page and "&gt;&gt;&gt;" in page  # the doctest block
    assert "Bases:" in page and "torchrl_recon.planners.SamplingPlanner" in page
    # a TensorDictModuleBase's own parameters, not tensordict's __new__(*args, **kwargs)
    policy = (html / "api/generated/torchrl_recon.policies.MPCPolicy.html").read_text()
    signature = policy.split('class="sig-paren">(', 1)[1].split('class="sig-paren">)', 1)[0]
    signature = re.sub(r"<[^>]+>", "", signature)
    assert signature.startswith("planner") and "threshold" in signature, signature[:200]


class Links(HTMLParser):
    """A page's ``href`` values and its element ids."""

    def __init__(self) -> None:
        super().__init__()
        self.hrefs: list[str] = []
        self.ids: set[str] = set()

    def handle_starttag(self, tag, attrs) -> None:
        attrs = dict(attrs)
        if attrs.get("id"):
            self.ids.add(attrs["id"])
        if tag in ("a", "link") and attrs.get("href"):
            self.hrefs.append(attrs["href"])


@pytest.mark.slow  # the Sphinx build (39 s); `make docs` builds it too
def test_internal_links_resolve(site):
    html, outcome = site
    pages = sorted(html.rglob("*.html"))
    assert len(pages) > 100, outcome["stderr"]
    parsed: dict[Path, Links] = {}

    def links(page: Path) -> Links:
        if page not in parsed:
            parsed[page] = Links()
            parsed[page].feed(page.read_text())
        return parsed[page]

    broken = []
    for page in pages:
        for href in links(page).hrefs:
            parts = urlsplit(href)
            if parts.scheme or parts.netloc:  # external: not checked (no network)
                continue
            target = (page.parent / unquote(parts.path)).resolve() if parts.path else page
            if target.is_dir():
                target = target / "index.html"
            if not target.exists():
                broken.append(f"{page.relative_to(html)}: {href}")
            elif parts.fragment and target.suffix == ".html":
                if unquote(parts.fragment) not in links(target).ids:
                    broken.append(f"{page.relative_to(html)}: {href} (no such anchor)")
    assert not broken, f"{len(broken)} broken internal links:\n" + "\n".join(broken[:50])


@pytest.mark.slow  # the Sphinx build (39 s); `make docs` builds it too
def test_guides_and_figures_are_in_the_site(site):
    html, _ = site
    guides = [p.relative_to(DOCS).with_suffix(".html") for p in DOCS.rglob("*.md")]
    guides = [g for g in guides if g.parts[0] not in ("results", "_build", "api")]
    assert guides and all((html / g).exists() for g in guides), guides
    index = (html / "index.html").read_text()
    for guide in guides:  # every guide is reachable from the landing page's navigation
        assert guide.name == "index.html" or f'href="{guide.as_posix()}"' in index, guide
    online = (html / "online.html").read_text()
    image = re.search(r'<img [^>]*src="([^"]*pendulum[^"]*\.png)"', online)
    assert image and (html / image.group(1)).exists()  # a published figure of docs/results


def load_conf():
    """docs/conf.py as a module (importing it writes nothing; a build's ``setup`` does)."""
    spec = importlib.util.spec_from_file_location("docs_conf", DOCS / "conf.py")
    conf = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(conf)
    return conf


def test_a_public_name_without_docstring_is_a_warning(caplog):
    conf = load_conf()
    lines: list[str] = []
    conf.process_docstring(None, "function", "torchrl_recon.envs.make_env", None, None, lines)
    assert "public name torchrl_recon.envs.make_env has no docstring" in caplog.text
    caplog.clear()
    lines = ["Make the env."]
    conf.process_docstring(None, "function", "torchrl_recon.envs.make_env", None, None, lines)
    assert "no docstring" not in caplog.text


def test_a_re_exported_constant_gets_its_docstring_from_where_it_is_assigned(caplog):
    conf = load_conf()
    from torchrl_recon.data import MASK_KEY

    lines = (tuple.__doc__ or "").splitlines()  # what autodoc finds: the value type's docstring
    conf.process_docstring(None, "data", "torchrl_recon.data.MASK_KEY", MASK_KEY, None, lines)
    assert "padded steps" in " ".join(lines) and "no docstring" not in caplog.text
