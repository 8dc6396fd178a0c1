"""Rigid links with ``<mesh>`` visuals (STL and OBJ files, loaded with trimesh) in a real browser:
drawn where the link is, in the U(C)RDF's material colour; a broken or missing mesh file is named
on the page and not drawn, never a crash."""

from __future__ import annotations

import io
import time

import numpy as np
import pytest
from view_helpers import ROOT, wait_for

pytestmark = pytest.mark.timeout(180)
trimesh = pytest.importorskip("trimesh", reason="the view extra (trimesh via viser) is missing")
Image = pytest.importorskip("PIL.Image", reason="Pillow (a dependency of viser) is missing")

GREEN = (0, 200, 0)  # nothing else on the page is this colour


def _robot_with_meshes(tmp_path, stl: str, obj: str) -> object:
    """hybrid_arm with its forearm drawn from an STL (green material) and its upper arm from
    an OBJ file (its own colour)."""
    text = (ROOT / "robots" / "hybrid_arm.ucrdf").read_text()
    forearm = '<geometry><cylinder radius="0.025" length="0.25"/></geometry>'
    upper = '<geometry><cylinder radius="0.03" length="0.3"/></geometry>'
    assert forearm in text and upper in text
    text = text.replace(
        forearm,
        f'<geometry><mesh filename="{stl}" scale="0.5 0.5 1"/></geometry>'
        '<material name="green"><color rgba="0 0.784 0 1"/></material>',
    )
    text = text.replace(upper, f'<geometry><mesh filename="file://{obj}"/></geometry>')
    path = tmp_path / "arm.ucrdf"
    path.write_text(text)
    return path


def _green_pixels(png: bytes) -> int:
    img = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)
    h, w = img.shape[:2]
    # the scene around the robot only: not the panel's green "Connected" icon (top right) nor
    # the orientation axes (bottom left)
    img = img[int(0.23 * h) : int(0.86 * h), int(0.17 * w) : int(0.6 * w)]
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    return int(((g > 90) & (g > 2 * r + 30) & (g > 2 * b + 30)).sum())


def _open(browser, app):
    ctx = browser.new_context(viewport={"width": 900, "height": 650})
    page = ctx.new_page()
    page.goto(app.url)
    page.get_by_text("tubes: 1").wait_for(timeout=60000)
    return ctx, page


def test_stl_and_obj_mesh_visuals_are_drawn_in_their_colour(tmp_path, browser):
    from view.app import ViewApp
    from view.source import OfflineSource

    meshes = tmp_path / "meshes"
    meshes.mkdir()
    box = trimesh.creation.box(extents=(0.1, 0.1, 0.25))  # a block where the forearm is
    box.export(meshes / "forearm.stl")
    cyl = trimesh.creation.cylinder(radius=0.03, height=0.3, sections=16)
    cyl.export(meshes / "upper.obj")
    path = _robot_with_meshes(tmp_path, "meshes/forearm.stl", str(meshes / "upper.obj"))
    app = ViewApp(OfflineSource(path).start(), port=0).start()
    ctx = None
    try:
        ctx, page = _open(browser, app)
        nodes = {k: v for k, v in app.nodes.items() if k.startswith("visual:")}
        stl = next(v for k, v in nodes.items() if "/forearm/" in k)
        obj = next(v for k, v in nodes.items() if "/upper_arm/" in k)
        # the files' geometry (STL scaled by its <mesh scale>), the material colour applied
        assert len(stl.vertices) == len(box.vertices)
        # the OBJ keeps its own colours: sent to the page as glTF, decoded back here
        sent = trimesh.load(io.BytesIO(obj.glb_data), file_type="glb", force="mesh")
        assert len(sent.faces) == len(cyl.faces)
        assert np.ptp(sent.vertices, axis=0) == pytest.approx(np.ptp(cyl.vertices, axis=0))
        extent = np.ptp(np.asarray(stl.vertices), axis=0)
        assert extent == pytest.approx([0.05, 0.05, 0.25], abs=1e-6)
        assert tuple(stl.color) == GREEN
        assert app.visual_problems == []
        time.sleep(1.0)
        assert wait_for(lambda: _green_pixels(page.locator("canvas").first.screenshot()) > 200, 20)
    finally:
        if ctx is not None:
            ctx.close()
        app.stop()


def test_a_missing_or_broken_mesh_is_named_on_the_page_and_not_drawn(tmp_path, browser):
    from view.app import ViewApp
    from view.source import OfflineSource

    (tmp_path / "broken.stl").write_bytes(b"solid nothing\nthis is not an STL\n")
    path = _robot_with_meshes(tmp_path, "broken.stl", str(tmp_path / "absent.obj"))
    app = ViewApp(OfflineSource(path).start(), port=0).start()
    ctx = None
    try:
        ctx, page = _open(browser, app)
        page.get_by_text("link upper_arm: mesh").wait_for(timeout=20000)
        page.get_by_text("link forearm: mesh").wait_for(timeout=20000)
        assert not any("/forearm/" in k or "/upper_arm/" in k for k in app.nodes)
        assert len(app.visual_problems) == 2, app.visual_problems
        time.sleep(1.0)
        assert _green_pixels(page.locator("canvas").first.screenshot()) == 0
    finally:
        if ctx is not None:
            ctx.close()
        app.stop()
