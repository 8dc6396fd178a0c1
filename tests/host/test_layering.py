"""The project's layering, read from the source: no import circle anywhere, and the daemon
package (what a Raspberry Pi installs) never imports the developer tools."""

from __future__ import annotations

from pathlib import Path

from import_graph import cycles, import_graph

REPO = Path(__file__).resolve().parents[2]


def test_no_import_cycle_anywhere_in_the_project():
    graph = import_graph(REPO)
    assert "host.config" in graph and "device/segment" in graph  # the walk sees the project
    found = cycles(graph)
    assert found == [], "import circles: " + "; ".join(" <-> ".join(c) for c in found)


def test_host_never_imports_tools():
    graph = import_graph(REPO)
    bad = sorted(
        f"{m} -> {t}"
        for m, targets in graph.items()
        if m == "host" or m.startswith("host.")
        for t in targets
        if t == "tools" or t.startswith("tools.")
    )
    assert bad == [], "host/ imports tools/: " + ", ".join(bad)
