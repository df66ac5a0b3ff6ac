#!/usr/bin/env python3
"""Writes the shipped scenes (cornell-box, cornell-box-point, corridor,
two-rooms) as OBJ + MTL + scene.toml.

The files are committed; rerun this script after editing it:
    python3 scenes/generate_scenes.py

Every quad is written with the winding that makes its front face (counter-
clockwise, as relight reads it) point where the scene needs it: into the room
for walls, outwards for solid boxes, down for the Cornell box light. Winding
matters only for emitters, but consistent winding keeps the data clean.
"""

from pathlib import Path

HERE = Path(__file__).resolve().parent


def sub(a, b):
    return [a[i] - b[i] for i in range(3)]


def cross(a, b):
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


def dot(a, b):
    return sum(a[i] * b[i] for i in range(3))


def centroid(points):
    return [sum(p[i] for p in points) / len(points) for i in range(3)]


class Obj:
    def __init__(self, mtl_name):
        self.lines = [f"mtllib {mtl_name}"]
        self.vertex_count = 0
        self.triangles = 0
        self.material = None

    def group(self, name, material):
        self.lines.append(f"o {name}")
        self.lines.append(f"usemtl {material}")

    def quad(self, points, facing):
        """Adds a planar quad whose normal points along `facing`."""
        normal = cross(sub(points[1], points[0]), sub(points[2], points[0]))
        if dot(normal, facing) < 0:
            points = list(reversed(points))
        first = self.vertex_count + 1
        for p in points:
            self.lines.append("v {:.4f} {:.4f} {:.4f}".format(*p))
        self.vertex_count += 4
        self.lines.append(f"f {first} {first + 1} {first + 2} {first + 3}")
        self.triangles += 2

    def cuboid(self, low, high, skip_bottom=False):
        """Axis-aligned box with outward-facing quads."""
        x0, y0, z0 = low
        x1, y1, z1 = high
        faces = [
            ([[x0, y1, z0], [x1, y1, z0], [x1, y1, z1], [x0, y1, z1]], [0, 1, 0]),
            ([[x0, y0, z0], [x1, y0, z0], [x1, y0, z1], [x0, y0, z1]], [0, -1, 0]),
            ([[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0]], [0, 0, -1]),
            ([[x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]], [0, 0, 1]),
            ([[x0, y0, z0], [x0, y1, z0], [x0, y1, z1], [x0, y0, z1]], [-1, 0, 0]),
            ([[x1, y0, z0], [x1, y1, z0], [x1, y1, z1], [x1, y0, z1]], [1, 0, 0]),
        ]
        for points, facing in faces:
            if skip_bottom and facing == [0, -1, 0]:
                continue
            self.quad(points, facing)

    def text(self, header):
        return "\n".join([f"# {header}"] + self.lines) + "\n"


def write_mtl(path, materials):
    lines = ["# Lambertian materials: Kd albedo (linear RGB), Ke emitted radiance W/(m^2 sr)."]
    for name, properties in materials.items():
        lines.append("")
        lines.append(f"newmtl {name}")
        for key, value in properties.items():
            lines.append(f"{key} " + " ".join(str(v) for v in value))
    path.write_text("\n".join(lines) + "\n")


def write(folder, obj, header, materials, scene):
    folder = HERE / folder
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "mesh.obj").write_text(obj.text(header))
    write_mtl(folder / "mesh.mtl", materials)
    (folder / "scene.toml").write_text(scene)
    print(f"{folder.name}: {obj.triangles} triangles")


# Cornell box data, Cornell University Program of Computer Graphics
# (https://www.graphics.cornell.edu/online/box/data.html), in millimetres.
CORNELL_WALLS = {
    "floor": ("white", [[552.8, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 559.2], [549.6, 0.0, 559.2]]),
    "ceiling": ("white", [[556.0, 548.8, 0.0], [556.0, 548.8, 559.2], [0.0, 548.8, 559.2], [0.0, 548.8, 0.0]]),
    "back_wall": ("white", [[549.6, 0.0, 559.2], [0.0, 0.0, 559.2], [0.0, 548.8, 559.2], [556.0, 548.8, 559.2]]),
    "right_wall": ("green", [[0.0, 0.0, 559.2], [0.0, 0.0, 0.0], [0.0, 548.8, 0.0], [0.0, 548.8, 559.2]]),
    "left_wall": ("red", [[552.8, 0.0, 0.0], [549.6, 0.0, 559.2], [556.0, 548.8, 559.2], [556.0, 548.8, 0.0]]),
}
CORNELL_SHORT_BLOCK = [
    [[130.0, 165.0, 65.0], [82.0, 165.0, 225.0], [240.0, 165.0, 272.0], [290.0, 165.0, 114.0]],
    [[290.0, 0.0, 114.0], [290.0, 165.0, 114.0], [240.0, 165.0, 272.0], [240.0, 0.0, 272.0]],
    [[130.0, 0.0, 65.0], [130.0, 165.0, 65.0], [290.0, 165.0, 114.0], [290.0, 0.0, 114.0]],
    [[82.0, 0.0, 225.0], [82.0, 165.0, 225.0], [130.0, 165.0, 65.0], [130.0, 0.0, 65.0]],
    [[240.0, 0.0, 272.0], [240.0, 165.0, 272.0], [82.0, 165.0, 225.0], [82.0, 0.0, 225.0]],
]
CORNELL_TALL_BLOCK = [
    [[423.0, 330.0, 247.0], [265.0, 330.0, 296.0], [314.0, 330.0, 456.0], [472.0, 330.0, 406.0]],
    [[423.0, 0.0, 247.0], [423.0, 330.0, 247.0], [472.0, 330.0, 406.0], [472.0, 0.0, 406.0]],
    [[472.0, 0.0, 406.0], [472.0, 330.0, 406.0], [314.0, 330.0, 456.0], [314.0, 0.0, 456.0]],
    [[314.0, 0.0, 456.0], [314.0, 330.0, 456.0], [265.0, 330.0, 296.0], [265.0, 0.0, 296.0]],
    [[265.0, 0.0, 296.0], [265.0, 330.0, 296.0], [423.0, 330.0, 247.0], [423.0, 0.0, 247.0]],
]
# The published light sits at y = 548.8 mm, in the ceiling plane; 0.1 mm lower
# keeps it from overlapping the ceiling.
CORNELL_LIGHT = [[343.0, 548.7, 227.0], [343.0, 548.7, 332.0], [213.0, 548.7, 332.0], [213.0, 548.7, 227.0]]

CORNELL_MATERIALS = {
    "white": {"Kd": [0.725, 0.71, 0.68]},
    "red": {"Kd": [0.63, 0.065, 0.05]},
    "green": {"Kd": [0.14, 0.45, 0.091]},
}

# One point light just under the ceiling's centre, in a black environment.
CORNELL_POINT_LIGHT = """[[lights]]
kind = "point"
position = [0.278, 0.5, 0.2795]
intensity = [0.25, 0.2125, 0.15]

[environment]
radiance = [0.0, 0.0, 0.0]
"""

CORNELL_CAMERA = """[camera]
eye = [0.278, 0.273, -0.8]
target = [0.278, 0.273, 0.0]
up = [0.0, 1.0, 0.0]
fov_y = 39.3077
resolution = [256, 256]
"""


def metres(points):
    return [[c / 1000.0 for c in p] for p in points]


def cornell(with_light):
    obj = Obj("mesh.mtl")
    box_centre = [0.278, 0.2744, 0.2796]
    for name, (material, points) in CORNELL_WALLS.items():
        points = metres(points)
        obj.group(name, material)
        obj.quad(points, sub(box_centre, centroid(points)))
    for name, block in [("short_block", CORNELL_SHORT_BLOCK), ("tall_block", CORNELL_TALL_BLOCK)]:
        faces = [metres(face) for face in block]
        block_centre = centroid([centroid(face) for face in faces])
        block_centre[1] = faces[0][0][1] / 2.0
        obj.group(name, "white")
        for face in faces:
            obj.quad(face, sub(centroid(face), block_centre))
    if with_light:
        obj.group("light", "light")
        obj.quad(metres(CORNELL_LIGHT), [0, -1, 0])
    return obj


def cornell_box():
    materials = dict(CORNELL_MATERIALS)
    materials["light"] = {"Kd": [0.78, 0.78, 0.78], "Ke": [17.0, 12.0, 4.0]}
    scene = f"""# The Cornell box (Cornell University measurements), in metres, lit by its
# emissive ceiling light (Ke in mesh.mtl).
mesh = "mesh.obj"

{CORNELL_CAMERA}
[environment]
radiance = [0.0, 0.0, 0.0]
"""
    write("cornell-box", cornell(True), "Cornell box with its area light, metres.", materials, scene)


def cornell_box_point():
    scene = f"""# The Cornell box geometry without the emissive quad, lit by one point light
# just under the ceiling centre.
mesh = "mesh.obj"

{CORNELL_CAMERA}
{CORNELL_POINT_LIGHT}"""
    write("cornell-box-point", cornell(False), "Cornell box without its area light, metres.", CORNELL_MATERIALS, scene)
    # The near field: a dimmer point light 0.1 m from one wall, or from the
    # three surfaces of a corner.
    near_field = {
        "scene-wall-light.toml": ("""# The point-lit Cornell box with its light 0.1 m from the red wall, in front
# of the tall block: most of the indirect light starts on a bright spot of
# wall close to the light, the near field that sparse light samples handle
# worst.""", [0.455, 0.42, 0.15]),
        "scene-corner-light.toml": ("""# The point-lit Cornell box with its light 0.1 m from the green wall, the
# back wall and the ceiling: three bright spots meeting in a corner, whose
# light the rest of the box receives only indirectly.""", [0.1, 0.4488, 0.4592]),
    }
    for file, (comment, position) in near_field.items():
        (HERE / "cornell-box-point" / file).write_text(f"""{comment}
mesh = "mesh.obj"

{CORNELL_CAMERA}
[[lights]]
kind = "point"
position = [{", ".join(str(c) for c in position)}]
intensity = [0.06, 0.051, 0.036]

[environment]
radiance = [0.0, 0.0, 0.0]
""")


def corridor():
    obj = Obj("mesh.mtl")
    half_width, height, length = 1.0, 2.5, 10.0
    x0, x1, y0, y1, z0, z1 = -half_width, half_width, 0.0, height, 0.0, length
    inside = [0.0, height / 2, length / 2]
    surfaces = [
        ("floor", "white", [[x0, y0, z0], [x1, y0, z0], [x1, y0, z1], [x0, y0, z1]]),
        ("ceiling", "white", [[x0, y1, z0], [x1, y1, z0], [x1, y1, z1], [x0, y1, z1]]),
        ("near_end", "white", [[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0]]),
        ("far_end", "white", [[x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]]),
        ("left_wall", "blue", [[x0, y0, z0], [x0, y1, z0], [x0, y1, z1], [x0, y0, z1]]),
        ("right_wall", "orange", [[x1, y0, z0], [x1, y1, z0], [x1, y1, z1], [x1, y0, z1]]),
    ]
    for name, material, points in surfaces:
        obj.group(name, material)
        obj.quad(points, sub(inside, centroid(points)))
    boxes = [
        ([-0.95, 0.0, 2.0], [-0.45, 0.8, 2.6]),
        ([0.40, 0.0, 4.5], [0.95, 1.2, 5.3]),
        ([-0.95, 0.0, 7.0], [-0.35, 0.6, 7.8]),
        ([0.50, 0.0, 8.5], [0.95, 1.8, 9.0]),
    ]
    for index, (low, high) in enumerate(boxes):
        obj.group(f"box_{index}", "white")
        obj.cuboid(low, high, skip_bottom=True)
    materials = {
        "white": {"Kd": [0.75, 0.75, 0.75]},
        "blue": {"Kd": [0.08, 0.15, 0.6]},
        "orange": {"Kd": [0.75, 0.35, 0.05]},
    }
    scene = """# A 2 m x 2.5 m x 10 m corridor with a blue (left) and an orange (right)
# wall and boxes near the walls, lit by a point light and a spot light.
mesh = "mesh.obj"

[camera]
eye = [0.0, 1.4, 0.2]
target = [0.0, 1.1, 10.0]
up = [0.0, 1.0, 0.0]
fov_y = 60.0
resolution = [320, 240]

[[lights]]
kind = "point"
position = [0.0, 2.3, 2.5]
intensity = [3.0, 2.85, 2.6]

[[lights]]
kind = "spot"
position = [0.0, 2.4, 7.0]
direction = [0.0, -1.0, 0.2]
intensity = [5.0, 4.7, 4.2]
inner_angle = 25.0
outer_angle = 40.0

[environment]
radiance = [0.0, 0.0, 0.0]
"""
    write("corridor", obj, "Corridor, metres.", materials, scene)


def two_rooms():
    """Two closed rooms of solid walls (boxes, 0.2 m thick) joined by a doorway.

    Room A: x in [0, 4]; shared wall x in [4, 4.2]; room B: x in [4.2, 8.2];
    both z in [0, 4], y in [0, 2.5]. The boxes overlap at every junction so no
    ray can slip through a crack between them.
    """
    obj = Obj("mesh.mtl")
    t = 0.2
    x_a0, x_a1, x_b0, x_b1 = 0.0, 4.0, 4.2, 8.2
    depth, height = 4.0, 2.5
    door_z0, door_z1, door_height = 1.5, 2.5, 2.1
    solids = [
        ("floor", "floor", [x_a0 - t, -t, -t], [x_b1 + t, 0.0, depth + t]),
        ("ceiling", "white", [x_a0 - t, height, -t], [x_b1 + t, height + t, depth + t]),
        ("wall_west", "white", [x_a0 - t, -t, -t], [x_a0, height + t, depth + t]),
        ("wall_east", "white", [x_b1, -t, -t], [x_b1 + t, height + t, depth + t]),
        ("wall_south", "white", [x_a0 - t, -t, -t], [x_b1 + t, height + t, 0.0]),
        ("wall_north", "white", [x_a0 - t, -t, depth], [x_b1 + t, height + t, depth + t]),
        ("shared_wall_south", "white", [x_a1, -t / 2, -t / 2], [x_b0, height + t / 2, door_z0]),
        ("shared_wall_north", "white", [x_a1, -t / 2, door_z1], [x_b0, height + t / 2, depth + t / 2]),
        ("lintel", "white", [x_a1, door_height, door_z0 - t / 2], [x_b0, height + t / 2, door_z1 + t / 2]),
    ]
    for name, material, low, high in solids:
        obj.group(name, material)
        obj.cuboid(low, high)
    materials = {
        "white": {"Kd": [0.75, 0.75, 0.75]},
        "floor": {"Kd": [0.5, 0.45, 0.4]},
    }
    scene = """# Two rooms joined by a doorway (x = 4 .. 4.2, z = 1.5 .. 2.5, up to 2.1 m).
# Only room A (x < 4) has a light; room B is lit indirectly through the door,
# so its far wall (x = 8.2) measures light leaks.
mesh = "mesh.obj"

[camera]
eye = [1.0, 1.3, 2.0]
target = [8.2, 1.0, 2.0]
up = [0.0, 1.0, 0.0]
fov_y = 50.0
resolution = [320, 240]

[[lights]]
kind = "point"
position = [1.5, 2.0, 1.0]
intensity = [3.0, 2.8, 2.5]

[environment]
radiance = [0.0, 0.0, 0.0]
"""
    write("two-rooms", obj, "Two rooms joined by a doorway, metres.", materials, scene)
    # The same rooms seen from inside the unlit one: its walls, floor and
    # ceiling fill the view, so leaks and blotches there dominate the image.
    unlit = scene.split("[camera]")[0].replace(
        "so its far wall (x = 8.2) measures light leaks.",
        "so its far wall (x = 8.2) measures light leaks. The camera stands in\n# room B's far corner and looks back at the doorway wall.",
    )
    unlit += """[camera]
eye = [7.9, 1.6, 3.7]
target = [4.2, 0.9, 0.6]
up = [0.0, 1.0, 0.0]
fov_y = 60.0
resolution = [320, 240]
"""
    unlit += "\n[[lights]]" + scene.split("[[lights]]")[1]
    (HERE / "two-rooms" / "scene-unlit-room.toml").write_text(unlit)


def moving_box():
    """A box floating through the point-lit Cornell box (LightSkin's moving
    meshes). Lives under sequences/ so that `relight demo`, which compares
    static scenes with the path tracer, does not pick it up."""
    folder = HERE / "sequences" / "moving-box"
    folder.mkdir(parents=True, exist_ok=True)
    obj = Obj("box.mtl")
    obj.group("box", "orange")
    obj.cuboid([-0.05, -0.05, -0.05], [0.05, 0.05, 0.05])
    (folder / "box.obj").write_text(obj.text("A 10 cm cube centred on its origin, metres."))
    write_mtl(folder / "box.mtl", {"orange": {"Kd": [0.8, 0.45, 0.1]}})
    scene = f"""# The point-lit Cornell box with an orange box floating across it, above
# the blocks and below the light, turning as it goes: render a sequence with
#   relight render scenes/sequences/moving-box/scene.toml -t lightskin --frames 8 -o box.png
mesh = "../../cornell-box-point/mesh.obj"

{CORNELL_CAMERA}
{CORNELL_POINT_LIGHT}
[[dynamic]]
mesh = "box.obj"
translation = [0.08, 0.4, 0.28]
rotation = [0.0, 0.0, 0.0]
# metres and degrees per frame
velocity = [0.05, 0.0, 0.0]
spin = [0.0, 10.0, 0.0]
"""
    (folder / "scene.toml").write_text(scene)
    print(f"sequences/moving-box: {obj.triangles} triangles")


if __name__ == "__main__":
    cornell_box()
    cornell_box_point()
    corridor()
    two_rooms()
    moving_box()
