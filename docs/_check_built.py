"""Offline checks of the built HTML documentation (run by .ci/docs after the Sphinx build).

1. Every name in ``evnoise.__all__`` has an entry in the API reference, and every subcommand of
   ``evnoise.cli.build_parser()`` a section in the CLI reference.
2. No internal link or image is broken: every relative ``href``/``src`` of every page must exist, and
   a ``#anchor`` must be an ``id`` (or ``name``) in the page it points into.
3. The gallery has at least ``MIN_EXAMPLES`` examples that were executed and made a figure.

Usage: ``python docs/_check_built.py [docs/_build/html]``. Prints one line per failure and exits 1
when there is any.
"""

from __future__ import annotations

import argparse
import sys
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import unquote, urlsplit

MIN_EXAMPLES = 8


class _Page(HTMLParser):
    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.ids: set[str] = set()
        self.links: list[tuple[str, str]] = []  # (attribute, value)
        self.images: list[str] = []

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        for key in ("id", "name"):
            if attrs.get(key):
                self.ids.add(attrs[key])
        if tag in ("a", "link") and attrs.get("href"):
            self.links.append(("href", attrs["href"]))
        if tag in ("img", "script", "source") and attrs.get("src"):
            self.links.append(("src", attrs["src"]))
            if tag == "img":
                self.images.append(attrs["src"])


def _parse(path: Path, cache: dict) -> _Page:
    if path not in cache:
        page = _Page()
        page.feed(path.read_text(encoding="utf-8", errors="replace"))
        cache[path] = page
    return cache[path]


def check_links(root: Path) -> list[str]:
    failures, cache = [], {}
    pages = sorted(root.rglob("*.html"))
    for page_path in pages:
        page = _parse(page_path, cache)
        for attr, value in page.links:
            parts = urlsplit(value)
            if parts.scheme or parts.netloc or value.startswith(("mailto:", "javascript:", "data:")):
                continue  # external: not checked offline
            rel = page_path.relative_to(root)
            if parts.path:
                target = (page_path.parent / unquote(parts.path)).resolve()
                if parts.path.endswith("/"):
                    target = target / "index.html"
                if not target.exists():
                    failures.append(f"{rel}: broken {attr} {value!r} (no {target.relative_to(root.resolve()) if target.is_relative_to(root.resolve()) else target})")
                    continue
            else:
                target = page_path.resolve()
            if parts.fragment and target.suffix == ".html":
                anchor = unquote(parts.fragment)
                if anchor not in _parse(target, cache).ids:
                    failures.append(f"{rel}: broken anchor {value!r} (no id {anchor!r} in "
                                    f"{target.relative_to(root.resolve())})")
    return failures


def check_reference(root: Path) -> list[str]:
    import argparse as _argparse

    import evnoise
    from evnoise.cli import build_parser

    failures = []
    api = root / "api"
    ids = set()
    cache: dict = {}
    for page in api.rglob("*.html"):
        ids |= _parse(page, cache).ids
    for name in evnoise.__all__:
        if f"evnoise.{name}" not in ids:
            failures.append(f"API reference: evnoise.{name} (in evnoise.__all__) has no entry "
                            f"(no id 'evnoise.{name}' under {api.relative_to(root)}/)")
    cli_page = root / "cli.html"
    if not cli_page.exists():
        return failures + ["CLI reference: cli.html was not built"]
    cli_ids = _parse(cli_page, cache).ids
    parser = build_parser()
    commands = [name for action in parser._actions if isinstance(action, _argparse._SubParsersAction)
                for name in action.choices]
    if not commands:
        failures.append("CLI reference: build_parser() has no subcommands")
    for name in commands:
        if f"evnoise-{name}" not in cli_ids:  # sphinx-argparse's section id of a subcommand
            failures.append(f"CLI reference: subcommand {name!r} has no section in cli.html")
    return failures


def check_gallery(root: Path) -> list[str]:
    gallery = root / "auto_examples"
    pages = sorted(p for p in gallery.glob("plot_*.html"))
    good = []
    failures = []
    for page in pages:
        parsed = _parse(page, {})
        figures = [s for s in parsed.images if "sphx_glr_" in s and not s.endswith("thumb.png")
                   and "/thumb/" not in s]
        if not figures:  # sphinx-gallery shows a figure only when the script ran and made it
            failures.append(f"gallery: {page.name} shows no figure (not executed?)")
        else:
            good.append(page.name)
    if len(good) < MIN_EXAMPLES:
        failures.append(f"gallery: {len(good)} executed examples with figures, at least {MIN_EXAMPLES} "
                        f"needed ({', '.join(good) or 'none'})")
    return failures


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", nargs="?", default=str(Path(__file__).parent / "_build" / "html"))
    args = ap.parse_args(argv)
    root = Path(args.root)
    if not (root / "index.html").exists():
        print(f"docs check: {root}/index.html not found: build the docs first", file=sys.stderr)
        return 1
    results = {"reference": check_reference(root), "links": check_links(root),
               "gallery": check_gallery(root)}
    n = 0
    for what, failures in results.items():
        for line in failures:
            print(f"FAIL [{what}] {line}", file=sys.stderr)
        n += len(failures)
        if not failures:
            print(f"ok   [{what}]")
    if n:
        print(f"docs check: {n} failure(s)", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
