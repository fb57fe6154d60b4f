"""A user's city as a Sionna RT scene: building footprints extruded to their heights (trimesh,
triangulated by mapbox-earcut) over a flat ground, written as PLY meshes and the Mitsuba XML
that ``sionna.rt.load_scene`` reads.

Materials are ITU-R P.2040 ones Sionna knows by name: concrete for walls and roofs (the
commonest facade; glass and brick differ by a few dB per reflection), medium-dry ground for the
ground plane, which reaches ``GROUND_MARGIN_M`` beyond the outermost building.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from xml.sax.saxutils import quoteattr

from deepsync.twin.raytrace.buildings import Building

BUILDING_MATERIAL = "concrete"
GROUND_MATERIAL = "medium_dry_ground"
MATERIAL_THICKNESS_M = 0.2  # a concrete wall; sets what refraction lets through
GROUND_MARGIN_M = 200.0


def write_city_scene(buildings: Sequence[Building], directory: str | Path) -> Path:
    """Write ``buildings.ply``, ``ground.ply`` and ``scene.xml`` into ``directory`` (made if
    missing) and return the XML's path."""
    import numpy as np  # noqa: PLC0415
    import trimesh  # noqa: PLC0415

    if not buildings:
        raise ValueError("a city scene needs at least one building")
    directory = Path(directory)
    (directory / "meshes").mkdir(parents=True, exist_ok=True)
    blocks = trimesh.util.concatenate([trimesh.creation.extrude_polygon(b.footprint, b.height_m)
                                       for b in buildings])
    blocks.fix_normals()  # outward faces: the solver needs to know which side is inside
    west, south, east, north = np.array([b.footprint.bounds for b in buildings]).T
    x0, y0 = west.min() - GROUND_MARGIN_M, south.min() - GROUND_MARGIN_M
    x1, y1 = east.max() + GROUND_MARGIN_M, north.max() + GROUND_MARGIN_M
    ground = trimesh.Trimesh(vertices=[[x0, y0, 0.0], [x1, y0, 0.0], [x1, y1, 0.0], [x0, y1, 0.0]],
                             faces=[[0, 1, 2], [0, 2, 3]])  # facing up
    shapes = {"buildings": (blocks, BUILDING_MATERIAL), "ground": (ground, GROUND_MATERIAL)}
    materials = sorted({material for _, material in shapes.values()})
    lines = ['<scene version="2.1.0">']
    for material in materials:
        lines += [f'    <bsdf type="itu-radio-material" id={quoteattr("mat-" + material)}>',
                  f'        <string name="type" value={quoteattr(material)}/>',
                  f'        <float name="thickness" value="{MATERIAL_THICKNESS_M}"/>',
                  '    </bsdf>']
    for name, (mesh, material) in shapes.items():
        mesh.export(directory / "meshes" / f"{name}.ply", file_type="ply")
        lines += [f'    <shape type="ply" id={quoteattr("mesh-" + name)}>',
                  f'        <string name="filename" value={quoteattr(f"meshes/{name}.ply")}/>',
                  '        <boolean name="face_normals" value="true"/>',
                  f'        <ref id={quoteattr("mat-" + material)} name="bsdf"/>',
                  '    </shape>']
    lines.append("</scene>")
    xml_path = directory / "scene.xml"
    xml_path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return xml_path
