"""Reading a `treetraits report` page as a reader's browser gets it: its headings, notes,
tables and the inline SVG figures (parsed as XML; the figures keep their text as text)."""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from html.parser import HTMLParser

SVG = "{http://www.w3.org/2000/svg}"


VOID = {"meta", "br", "img", "hr", "link", "input", "col", "wbr", "source"}


class Page(HTMLParser):
    """The page's title, headings, notes, table cells (by table) and outside links, and
    its figures."""

    def __init__(self) -> None:
        super().__init__()
        self.title = ""
        self.headings: list[str] = []
        self.notes: list[str] = []
        self.items: list[str] = []  # list items
        self.tables: list[list[list[str]]] = []  # table -> row -> cells, the header first
        self.links: list[str] = []  # every href/src that is not in the page
        self.figures: dict[str, ET.Element] = {}
        self._open: list[tuple[str, str, list[str]]] = []  # tag, class, its text

    @classmethod
    def read(cls, text: str) -> Page:
        page = cls()
        page.feed(text)
        page.close()
        page.figures = figures(text)
        return page

    def handle_starttag(self, tag: str, attrs: list) -> None:
        attrs = dict(attrs)
        for name in ("href", "src", "xlink:href"):
            if name in attrs and not attrs[name].startswith(("data:", "#")):
                self.links.append(attrs[name])
        if tag == "table":
            self.tables.append([])
        elif tag == "tr" and self.tables:
            self.tables[-1].append([])
        if tag not in VOID:
            self._open.append((tag, attrs.get("class") or "", []))

    def handle_startendtag(self, tag: str, attrs: list) -> None:
        self.handle_starttag(tag, attrs)
        if tag not in VOID:
            self._open.pop()

    def handle_data(self, data: str) -> None:
        for _, _, text in self._open:  # an element's text holds its children's
            text.append(data)

    def handle_endtag(self, tag: str) -> None:
        while self._open:
            name, classes, parts = self._open.pop()
            if name == tag:
                break
        else:
            return
        text = " ".join("".join(parts).split())
        if tag == "title" and not self.title:
            self.title = text
        elif tag in ("h1", "h2"):
            self.headings.append(text)
        elif tag in ("td", "th") and self.tables and self.tables[-1]:
            self.tables[-1][-1].append(text)
        elif tag == "p" and "note" in classes.split():
            self.notes.append(text)
        elif tag == "li":
            self.items.append(text)

    def table(self, first_header: str) -> list[list[str]]:
        """The table whose first header cell is `first_header`: header row first."""
        return next(t for t in self.tables if t and t[0] and t[0][0] == first_header)

    def facts(self) -> dict[str, str]:
        return {row[0]: row[1] for row in self.tables[0]}


def figures(text: str) -> dict[str, ET.Element]:
    """The page's inline SVG figures by name (each id of a figure is `<name>-...`)."""
    found = {}
    for block in re.findall(r"<svg\b.*?</svg>", text, flags=re.S):
        root = ET.fromstring(block)
        first = root.find(f".//{SVG}g[@id]")
        name = first.get("id").rsplit("-figure_", 1)[0]
        found[name] = root
    return found


def by_id(root: ET.Element, element_id: str) -> ET.Element | None:
    return root.find(f".//*[@id='{element_id}']")


def texts(element: ET.Element) -> list[str]:
    """The text elements' contents under `element`, in document order."""
    return [(t.text or "").strip() for t in element.iter(f"{SVG}text")]


def fill(element: ET.Element) -> tuple[float, float, float]:
    """The fill of the first drawn shape or text under `element` (SVG's default: black)."""
    for node in element.iter():
        if node.tag in (f"{SVG}path", f"{SVG}text", f"{SVG}use"):
            match = re.search(r"fill:\s*#([0-9a-fA-F]{6})", node.get("style") or "")
            if match is None:
                return (0.0, 0.0, 0.0)
            value = match.group(1)
            return tuple(int(value[i : i + 2], 16) / 255 for i in (0, 2, 4))
    raise AssertionError("nothing drawn under the element")


def contrast(a: tuple[float, ...], b: tuple[float, ...]) -> float:
    """WCAG 2's contrast ratio of two sRGB colours (written out here, not imported: the
    test checks the page against the standard, not against the report's own code)."""

    def luminance(rgb: tuple[float, ...]) -> float:
        lin = [c / 12.92 if c <= 0.04045 else ((c + 0.055) / 1.055) ** 2.4 for c in rgb]
        return 0.2126 * lin[0] + 0.7152 * lin[1] + 0.0722 * lin[2]

    high, low = sorted((luminance(a), luminance(b)), reverse=True)
    return (high + 0.05) / (low + 0.05)
