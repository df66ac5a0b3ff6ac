#!/usr/bin/env python3
"""Cross-check relight's ground-truth path tracer against Mitsuba 3.

What it checks
--------------
relight's ``reference`` technique is an unbiased path tracer that every other
technique is measured against, so it must itself agree with an independent
renderer.  This script renders the same scene with relight and with Mitsuba 3
(variant ``scalar_rgb``, plain RGB arithmetic, no spectral conversion) and
compares the two full images (emission seen directly + direct + indirect
light):

* the scene file (TOML) and its OBJ/MTL mesh are read here, independently of
  relight's loader, and turned into a Mitsuba scene dictionary: one flat-shaded
  triangle mesh per material with a two-sided Lambertian BSDF of albedo ``Kd``
  and, when ``Ke`` is non-zero, a one-sided area emitter of radiance ``Ke``
  (front face = counter-clockwise winding, like relight); point lights,
  directional lights and the constant environment map to Mitsuba's ``point``,
  ``directional`` and ``constant`` emitters with the same units;
* the camera is a pinhole with vertical field of view, gluLookAt convention
  (right = forward x up), pixel (0, 0) at the top left.  Mitsuba's ``look_at``
  uses the same convention (its camera-space +x is the image's left), so the
  images are compared pixel for pixel without any flip;
* relight's ``--max-bounces B`` (0 = direct light only) is Mitsuba's
  ``max_depth = B + 2`` (1 = emitters seen directly, 2 = direct light).
  The default B is relight's own default, 64, so the check covers the
  reference as the project uses it; there the last bounces carry almost no
  energy, so run once more with ``--max-bounces 0`` (and 1) to check the
  bounce mapping and the direct light on their own.

Why the bound is what it is
---------------------------
Both renderers are unbiased Monte Carlo estimators of the same image, so the
difference of two renders is zero-mean noise plus any systematic disagreement
``b``: ``E|R - M|^2 = Var(R) + Var(M) + |b|^2``.  The script measures the
noise instead of guessing it.  It renders relight twice (seeds 1 and 2) and
Mitsuba twice (seeds 0 and 1); two renders of one renderer differ by pure noise,
``E|X1 - X2|^2 = 2 Var(X)``, so the relRMSE expected from noise alone between
one relight and one Mitsuba render (the "noise floor") is

    noise_floor = sqrt((relRMSE(R1, R2)^2 + relRMSE(M0, M1)^2) / 2)

and relight's first render is compared with Mitsuba's first against

    bound = noise_floor * NOISE_FACTOR + SYSTEMATIC_ALLOWANCE

NOISE_FACTOR = 1.5 covers the sampling fluctuation of both the noise floor
and the compared relRMSE (each from one pair of images: on the Cornell box
the block-averaged pair values vary by up to a factor of two between seeds).
SYSTEMATIC_ALLOWANCE = 0.02 covers legitimate differences: ray offsets at
the box's corners and float rounding (``scalar_rgb`` is plain RGB, so no
spectral difference is expected).  With ``--relight-image`` there is only
one relight render and relight's variance is taken to equal Mitsuba's.

relRMSE is an L2 norm, so the brightest pixels dominate it: in the area-lit
Cornell box the directly seen light (radiance ~12.6 over ~560 pixels) holds
99 % of the image's squared norm, and a relight rendering one bounce too many
at ``--max-bounces 0`` (16 % brighter walls) still passed a full-image check.  So three views of the
images are compared, each with its own measured noise floor and bound, and
all three must pass:

* "full image": every pixel (the comparison the project defines; it checks
  the emitters' size, position and radiance as seen by the camera);
* "lit surfaces": pixels that see emission directly (found with a Mitsuba
  ``max_depth = 1`` render, dilated by one pixel) are set to zero in all
  images, leaving the direct and indirect light on the surfaces;
* "surfaces BxB": the lit surfaces averaged over BLOCK x BLOCK tiles
  (default 8 x 8).  Averaging divides the noise relRMSE by about BLOCK
  while a systematic difference (wrong light units, an off-by-one bounce
  count, a mirrored image, a wrong field of view, emission from the wrong
  side) keeps its size, so here the 0.02 allowance dominates the bound: at
  the default 128 spp a uniform 5 % error fails, which the per-pixel views
  alone would let through.

Exit status: 0 = agree, 1 = a relRMSE above its bound, 2 = usage or input
error (including relight failing to run).

Usage:
    python tools/cross_check_mitsuba.py scenes/cornell-box/scene.toml \\
        [--relight target/release/relight] [--spp 128] [--max-bounces 64] \\
        [--out out/cross-check] [--bound X] [--surface-bound X] [--block-bound X]

Requires only ``mitsuba==3.9.1`` and ``numpy`` (Python >= 3.11 for tomllib).
"""

from __future__ import annotations

import argparse
import math
import shutil
import subprocess
import sys
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

NOISE_FACTOR = 1.5
SYSTEMATIC_ALLOWANCE = 0.02
DEFAULT_SPP = 128
# relight's own default for `relight render --max-bounces`.
DEFAULT_MAX_BOUNCES = 64
DEFAULT_BLOCK = 8
# The first seed of each pair renders the compared image; the second measures the noise.
MITSUBA_SEEDS = (0, 1)
RELIGHT_SEEDS = (1, 2)
EMITTER_MASK_SPP = 16
# relight's Material::default(), used for faces without a (known) material.
DEFAULT_ALBEDO = (0.5, 0.5, 0.5)
# relight's defaults for the optional [camera] keys (eye, target and fov_y are required).
DEFAULT_CAMERA_UP = [0.0, 1.0, 0.0]
DEFAULT_CAMERA_RESOLUTION = [256, 256]
REPOSITORY_ROOT = Path(__file__).resolve().parent.parent


class InputError(Exception):
    """A problem with the command line or the scene; exit status 2."""


# --------------------------------------------------------------------------
# Scene file and OBJ/MTL reading
# --------------------------------------------------------------------------


@dataclass
class MaterialDescription:
    name: str
    albedo: tuple[float, float, float] = DEFAULT_ALBEDO
    emission: tuple[float, float, float] = (0.0, 0.0, 0.0)
    texture: str | None = None


@dataclass
class CameraDescription:
    eye: list[float]
    target: list[float]
    up: list[float]
    fov_y_degrees: float
    width: int
    height: int


@dataclass
class SceneDescription:
    source: Path
    mesh_path: Path
    camera: CameraDescription
    lights: list[dict]
    environment_radiance: list[float]
    # Every OBJ vertex position (N x 3); triangles index it, grouped by material name.
    positions: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    triangles_by_material: dict[str, list[tuple[int, int, int]]] = field(default_factory=dict)
    materials: dict[str, MaterialDescription] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)


def read_vector(table: dict, key: str, length: int, context: str, default=None) -> list[float]:
    value = table.get(key, default)
    if value is None:
        raise InputError(f"{context}: missing '{key}'")
    if not isinstance(value, list) or len(value) != length:
        raise InputError(f"{context}: '{key}' must be an array of {length} numbers, got {value!r}")
    try:
        numbers = [float(component) for component in value]
    except (TypeError, ValueError):
        raise InputError(f"{context}: '{key}' must contain numbers, got {value!r}") from None
    if not all(math.isfinite(number) for number in numbers):
        raise InputError(f"{context}: '{key}' must be finite, got {value!r}")
    return numbers


def read_radiometric(table: dict, key: str, context: str, default=None) -> list[float]:
    colour = read_vector(table, key, 3, context, default)
    if min(colour) < 0.0:
        raise InputError(f"{context}: '{key}' must be non-negative, got {colour}")
    return colour


def read_scene_file(scene_path: Path) -> SceneDescription:
    try:
        with open(scene_path, "rb") as scene_file:
            document = tomllib.load(scene_file)
    except OSError as error:
        raise InputError(f"cannot read scene file {scene_path}: {error}") from None
    except tomllib.TOMLDecodeError as error:
        raise InputError(f"{scene_path}: invalid TOML: {error}") from None

    mesh_name = document.get("mesh")
    if not isinstance(mesh_name, str) or not mesh_name:
        raise InputError(f"{scene_path}: missing top-level 'mesh = \"file.obj\"'")
    mesh_path = (scene_path.parent / mesh_name).resolve()
    extension = mesh_path.suffix.lower()
    if extension in (".gltf", ".glb"):
        raise InputError(
            f"{scene_path}: mesh '{mesh_name}' is glTF; the Mitsuba cross-check only "
            "supports OBJ/MTL scenes (convert the scene to OBJ to cross-check it)"
        )
    if extension != ".obj":
        raise InputError(f"{scene_path}: mesh '{mesh_name}' is not an .obj file")

    camera_table = document.get("camera")
    if camera_table is None:
        raise InputError(
            f"{scene_path}: no [camera]; relight then frames the scene automatically, which this "
            "cross-check does not reproduce: add a [camera] table"
        )
    if not isinstance(camera_table, dict):
        raise InputError(f"{scene_path}: [camera] must be a table")
    context = f"{scene_path} [camera]"
    resolution = camera_table.get("resolution", DEFAULT_CAMERA_RESOLUTION)
    if (
        not isinstance(resolution, list)
        or len(resolution) != 2
        or not all(isinstance(size, int) and size > 0 for size in resolution)
    ):
        raise InputError(f"{context}: 'resolution' must be [width, height] positive integers")
    fov_y = camera_table.get("fov_y")
    if isinstance(fov_y, bool) or not isinstance(fov_y, (int, float)) or not 0.0 < float(fov_y) < 180.0:
        raise InputError(f"{context}: 'fov_y' must be a number of degrees in (0, 180)")
    camera = CameraDescription(
        eye=read_vector(camera_table, "eye", 3, context),
        target=read_vector(camera_table, "target", 3, context),
        up=read_vector(camera_table, "up", 3, context, DEFAULT_CAMERA_UP),
        fov_y_degrees=float(fov_y),
        width=resolution[0],
        height=resolution[1],
    )
    forward = np.subtract(camera.target, camera.eye)
    if np.linalg.norm(forward) == 0.0 or np.linalg.norm(np.cross(forward, camera.up)) < 1e-9 * np.linalg.norm(forward):
        raise InputError(f"{context}: eye, target and up do not define a camera frame")

    lights = []
    light_tables = document.get("lights", [])
    if not isinstance(light_tables, list):
        raise InputError(f"{scene_path}: 'lights' must be an array of tables ([[lights]])")
    for light_index, light_table in enumerate(light_tables):
        context = f"{scene_path} [[lights]] #{light_index + 1}"
        kind = light_table.get("kind")
        if kind == "point":
            lights.append({
                "kind": "point",
                "position": read_vector(light_table, "position", 3, context),
                "intensity": read_radiometric(light_table, "intensity", context),
            })
        elif kind == "directional":
            direction = read_vector(light_table, "direction", 3, context)
            if np.linalg.norm(direction) == 0.0:
                raise InputError(f"{context}: 'direction' must be non-zero")
            lights.append({
                "kind": "directional",
                "direction": direction,
                "irradiance": read_radiometric(light_table, "irradiance", context),
            })
        elif kind == "spot":
            raise InputError(
                f"{context}: spot lights are not cross-checked: Mitsuba's 'spot' emitter "
                "has its own angular falloff between beam_width and cutoff_angle, not relight's "
                "smoothstep between inner and outer angle, so the images would differ by design"
            )
        else:
            raise InputError(f"{context}: unknown light kind {kind!r}")

    environment_table = document.get("environment", {})
    if not isinstance(environment_table, dict):
        raise InputError(f"{scene_path}: [environment] must be a table")
    environment_radiance = read_radiometric(
        environment_table, "radiance", f"{scene_path} [environment]", [0.0, 0.0, 0.0]
    )

    scene = SceneDescription(
        source=scene_path,
        mesh_path=mesh_path,
        camera=camera,
        lights=lights,
        environment_radiance=environment_radiance,
    )
    read_obj(scene)
    return scene


def parse_colour(fields: list[str], context: str) -> tuple[float, float, float]:
    try:
        values = [float(value) for value in fields[:3]]
    except ValueError:
        raise InputError(f"{context}: expected numbers, got {' '.join(fields)!r}") from None
    if len(values) == 1:
        values = values * 3
    if len(values) != 3:
        raise InputError(f"{context}: expected 1 or 3 numbers")
    return (values[0], values[1], values[2])


def read_mtl(mtl_path: Path, materials: dict[str, MaterialDescription], warnings: list[str]) -> None:
    try:
        text = mtl_path.read_text(encoding="utf-8", errors="replace")
    except OSError as error:
        warnings.append(f"cannot read material library {mtl_path}: {error}")
        return
    current: MaterialDescription | None = None
    for line_number, raw_line in enumerate(text.splitlines(), start=1):
        line = raw_line.split("#", 1)[0].strip()
        if not line:
            continue
        keyword, _, rest = line.replace("\t", " ").partition(" ")
        rest = rest.strip()
        fields = rest.split()
        context = f"{mtl_path}:{line_number}"
        if keyword == "newmtl":
            name = rest.strip()
            current = MaterialDescription(name=name)
            materials[name] = current
        elif current is None:
            continue
        elif keyword == "Kd":
            # relight clamps albedo to 1 (with a warning) to keep energy conservation.
            current.albedo = tuple(min(value, 1.0) for value in parse_colour(fields, context))
        elif keyword == "Ke":
            current.emission = parse_colour(fields, context)
        elif keyword == "map_Kd" and fields:
            current.texture = fields[-1]


def resolve_obj_index(token: str, vertex_count: int, context: str) -> int:
    position_token = token.split("/", 1)[0]
    try:
        index = int(position_token)
    except ValueError:
        raise InputError(f"{context}: bad face index {token!r}") from None
    if index > 0:
        resolved = index - 1
    elif index < 0:
        resolved = vertex_count + index
    else:
        raise InputError(f"{context}: face index 0 is invalid in OBJ")
    if not 0 <= resolved < vertex_count:
        raise InputError(f"{context}: face index {index} out of range ({vertex_count} vertices so far)")
    return resolved


def read_obj(scene: SceneDescription) -> None:
    """Fill positions, per-material triangles and materials from the OBJ and its MTL files."""
    obj_path = scene.mesh_path
    try:
        text = obj_path.read_text(encoding="utf-8", errors="replace")
    except OSError as error:
        raise InputError(f"cannot read mesh {obj_path}: {error}") from None
    positions: list[tuple[float, float, float]] = []
    current_material = "default"
    triangles_by_material: dict[str, list[tuple[int, int, int]]] = {}
    for line_number, raw_line in enumerate(text.splitlines(), start=1):
        line = raw_line.split("#", 1)[0].strip()
        if not line:
            continue
        keyword, _, rest = line.replace("\t", " ").partition(" ")
        rest = rest.strip()
        fields = rest.split()
        context = f"{obj_path}:{line_number}"
        if keyword == "v":
            if len(fields) < 3:
                raise InputError(f"{context}: vertex needs 3 coordinates")
            try:
                coordinates = [float(value) for value in fields]
            except ValueError:
                raise InputError(f"{context}: bad vertex {rest!r}") from None
            # "v x y z w" is homogeneous (relight divides by w); "v x y z r g b" has a colour.
            weight = coordinates[3] if len(coordinates) == 4 else 1.0
            if weight == 0.0:
                raise InputError(f"{context}: vertex weight w = 0")
            positions.append(tuple(coordinate / weight for coordinate in coordinates[:3]))
        elif keyword == "f":
            if len(fields) < 3:
                raise InputError(f"{context}: face needs at least 3 vertices")
            corners = [resolve_obj_index(token, len(positions), context) for token in fields]
            face_list = triangles_by_material.setdefault(current_material, [])
            # Polygon fan triangulation around the first corner.
            for corner in range(1, len(corners) - 1):
                face_list.append((corners[0], corners[corner], corners[corner + 1]))
        elif keyword == "usemtl":
            current_material = rest.strip() or "default"
        elif keyword == "mtllib":
            library = rest.strip()
            candidates = [library] if (obj_path.parent / library).is_file() else fields
            for candidate in candidates:
                read_mtl(obj_path.parent / candidate, scene.materials, scene.warnings)
    if not triangles_by_material:
        raise InputError(f"{obj_path}: no faces")

    scene.positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    dropped = 0
    for material_name, triangles in triangles_by_material.items():
        if material_name not in scene.materials:
            if material_name != "default":
                scene.warnings.append(
                    f"material '{material_name}' is not in any MTL file; using albedo {DEFAULT_ALBEDO}"
                )
            scene.materials[material_name] = MaterialDescription(name=material_name)
        material = scene.materials[material_name]
        if material.texture is not None:
            raise InputError(
                f"material '{material_name}' has an albedo texture ({material.texture}); the "
                "cross-check compares untextured Lambertian scenes only"
            )
        kept = []
        for triangle in triangles:
            corner_a, corner_b, corner_c = (scene.positions[index] for index in triangle)
            if np.linalg.norm(np.cross(corner_b - corner_a, corner_c - corner_a)) > 0.0:
                kept.append(triangle)
            else:
                dropped += 1
        if kept:
            scene.triangles_by_material[material_name] = kept
    if dropped:
        scene.warnings.append(f"dropped {dropped} degenerate triangle(s)")


# --------------------------------------------------------------------------
# Mitsuba scene
# --------------------------------------------------------------------------


def import_mitsuba():
    try:
        import mitsuba
    except ImportError:
        raise InputError(
            "cannot import mitsuba; install it with `pip install mitsuba==3.9.1 numpy` "
            f"into the Python running this script ({sys.executable})"
        ) from None
    mitsuba.set_variant("scalar_rgb")
    return mitsuba


def build_material_mesh(mitsuba, scene: SceneDescription, material_name: str):
    """One Mitsuba mesh per material: flat shaded (no vertex normals), two-sided diffuse, optional area emitter."""
    triangles = np.asarray(scene.triangles_by_material[material_name], dtype=np.int64)
    used_vertices, remapped = np.unique(triangles.ravel(), return_inverse=True)
    vertex_positions = scene.positions[used_vertices].astype(np.float32)
    faces = remapped.reshape(-1, 3).astype(np.uint32)
    material = scene.materials[material_name]

    properties = mitsuba.Properties()
    properties["bsdf"] = mitsuba.load_dict({
        "type": "twosided",
        "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": list(material.albedo)}},
    })
    if max(material.emission) > 0.0:
        # Mitsuba's area emitter radiates on the side of the geometric normal
        # (v1 - v0) x (v2 - v0), i.e. counter-clockwise winding, like relight.
        properties["emitter"] = mitsuba.load_dict({
            "type": "area",
            "radiance": {"type": "rgb", "value": list(material.emission)},
        })
    mesh = mitsuba.Mesh(
        f"material_{material_name}",
        len(vertex_positions),
        len(faces),
        props=properties,
        has_vertex_normals=False,
        has_vertex_texcoords=False,
    )
    parameters = mitsuba.traverse(mesh)
    parameters["vertex_positions"] = vertex_positions.ravel()
    parameters["faces"] = faces.ravel()
    parameters.update()
    return mesh


def mitsuba_max_depth(relight_max_bounces: int) -> int:
    """relight counts indirect bounces (0 = direct light only); Mitsuba counts
    path segments (1 = emitters seen directly, 2 = direct light)."""
    return relight_max_bounces + 2


def build_mitsuba_scene(mitsuba, scene: SceneDescription, spp: int, max_depth: int):
    camera = scene.camera
    scene_dictionary = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": max_depth, "hide_emitters": False},
        "sensor": {
            "type": "perspective",
            "fov_axis": "y",
            "fov": camera.fov_y_degrees,
            "near_clip": 1e-4,
            "far_clip": 1e6,
            # look_at: camera-space +x = up x forward is the image's left, so
            # image right = forward x up, the gluLookAt convention relight uses.
            "to_world": mitsuba.ScalarTransform4f().look_at(
                origin=camera.eye, target=camera.target, up=camera.up
            ),
            "sampler": {"type": "independent", "sample_count": spp},
            "film": {
                "type": "hdrfilm",
                "width": camera.width,
                "height": camera.height,
                "pixel_format": "rgb",
                "component_format": "float32",
                "rfilter": {"type": "box"},
            },
        },
    }
    for mesh_index, material_name in enumerate(scene.triangles_by_material):
        scene_dictionary[f"mesh_{mesh_index}"] = build_material_mesh(mitsuba, scene, material_name)
    for light_index, light in enumerate(scene.lights):
        if light["kind"] == "point":
            scene_dictionary[f"light_{light_index}"] = {
                "type": "point",
                "position": light["position"],
                "intensity": {"type": "rgb", "value": light["intensity"]},
            }
        else:
            scene_dictionary[f"light_{light_index}"] = {
                "type": "directional",
                "direction": light["direction"],
                "irradiance": {"type": "rgb", "value": light["irradiance"]},
            }
    if max(scene.environment_radiance) > 0.0:
        scene_dictionary["environment"] = {
            "type": "constant",
            "radiance": {"type": "rgb", "value": scene.environment_radiance},
        }
    return mitsuba.load_dict(scene_dictionary)


def render_mitsuba(mitsuba, mitsuba_scene, spp: int, seed: int) -> np.ndarray:
    image = mitsuba.render(mitsuba_scene, spp=spp, seed=seed)
    return np.array(image, dtype=np.float64)[:, :, :3]


# --------------------------------------------------------------------------
# relight
# --------------------------------------------------------------------------


def find_relight_binary(requested: str | None) -> str:
    if requested:
        path = Path(requested)
        if path.is_file():
            return str(path.resolve())
        found = shutil.which(requested)
        if found:
            return found
        raise InputError(f"relight binary {requested!r} not found")
    for candidate in (REPOSITORY_ROOT / "target" / "release" / "relight", REPOSITORY_ROOT / "target" / "debug" / "relight"):
        if candidate.is_file():
            return str(candidate)
    found = shutil.which("relight")
    if found:
        return found
    raise InputError(
        "no relight binary: build it with `cargo build --release -p relight-cli` or pass --relight PATH"
    )


def run_relight(relight_binary: str, scene_path: Path, spp: int, max_bounces: int, seed: int, output_path: Path) -> None:
    command = [
        relight_binary, "render", str(scene_path),
        "--technique", "reference",
        "--spp", str(spp),
        "--max-bounces", str(max_bounces),
        "--seed", str(seed),
        "-o", str(output_path),
        "--quiet",
    ]
    print("running:", " ".join(command), flush=True)
    completed = subprocess.run(command, capture_output=True, text=True)
    if completed.returncode != 0:
        raise InputError(
            f"relight failed with status {completed.returncode}:\n{completed.stderr.strip() or completed.stdout.strip()}"
        )


def read_exr_rgb(mitsuba, exr_path: Path) -> np.ndarray:
    try:
        bitmap = mitsuba.Bitmap(str(exr_path))
    except Exception as error:  # Mitsuba raises RuntimeError with the reason.
        raise InputError(f"cannot read {exr_path}: {error}") from None
    bitmap = bitmap.convert(mitsuba.Bitmap.PixelFormat.RGB, mitsuba.Struct.Type.Float32, srgb_gamma=False)
    return np.array(bitmap, dtype=np.float64).reshape(bitmap.height(), bitmap.width(), 3)


# --------------------------------------------------------------------------
# Comparison and output
# --------------------------------------------------------------------------


def relative_rmse(test: np.ndarray, reference: np.ndarray) -> float:
    """relight's definition: L2 norm of the error over the L2 norm of the reference."""
    reference_norm = math.sqrt(float(np.sum(reference * reference)))
    if reference_norm == 0.0:
        return 0.0 if not np.any(test) else math.inf
    return math.sqrt(float(np.sum((test - reference) ** 2))) / reference_norm


def block_average(image: np.ndarray, block: int) -> np.ndarray:
    """Mean over block x block pixel tiles (a partial edge tile is dropped)."""
    height = image.shape[0] // block * block
    width = image.shape[1] // block * block
    cropped = image[:height, :width]
    return cropped.reshape(height // block, block, width // block, block, -1).mean(axis=(1, 3))


def luminance(image: np.ndarray) -> np.ndarray:
    return image @ np.array([0.2126, 0.7152, 0.0722])


def write_png(mitsuba, image: np.ndarray, path: Path) -> None:
    bitmap = mitsuba.Bitmap(np.ascontiguousarray(np.clip(image, 0.0, None), dtype=np.float32))
    bitmap.convert(mitsuba.Bitmap.PixelFormat.RGB, mitsuba.Struct.Type.UInt8, srgb_gamma=True).write(str(path))


def write_exr(mitsuba, image: np.ndarray, path: Path) -> None:
    mitsuba.Bitmap(np.ascontiguousarray(image, dtype=np.float32)).write(str(path))


def signed_false_colour(difference: np.ndarray, full_scale: float) -> np.ndarray:
    """Red where relight is brighter, blue where darker; saturated at +-full_scale."""
    normalised = np.clip(difference / full_scale, -1.0, 1.0) if full_scale > 0.0 else np.zeros_like(difference)
    colour = np.ones(difference.shape + (3,))
    positive = np.clip(normalised, 0.0, 1.0)
    negative = np.clip(-normalised, 0.0, 1.0)
    colour[..., 1] -= positive + negative
    colour[..., 2] -= positive
    colour[..., 0] -= negative
    return np.clip(colour, 0.0, 1.0)


def emitter_mask(mitsuba, scene: SceneDescription) -> np.ndarray:
    """Pixels that see emission directly (emissive triangles or the environment),
    dilated by one pixel so that partly covered edge pixels are included."""
    emission_scene = build_mitsuba_scene(mitsuba, scene, EMITTER_MASK_SPP, 1)
    emission = render_mitsuba(mitsuba, emission_scene, EMITTER_MASK_SPP, MITSUBA_SEEDS[0])
    seen = np.any(emission > 0.0, axis=2)
    padded = np.pad(seen, 1)
    dilated = np.zeros_like(seen)
    for row_shift in (0, 1, 2):
        for column_shift in (0, 1, 2):
            dilated |= padded[row_shift:row_shift + seen.shape[0], column_shift:column_shift + seen.shape[1]]
    return dilated


def write_difference_images(
    mitsuba, relight_image, mitsuba_image, surface_mask, block: int, output_directory: Path
) -> list[Path]:
    mean_luminance = float(luminance(mitsuba_image[surface_mask]).mean()) if surface_mask.any() else 0.0
    scale = mean_luminance if mean_luminance > 0.0 else 1.0
    absolute_path = output_directory / "difference_abs.png"
    # |relight - Mitsuba| per pixel; 1.0 (white) = the lit surfaces' mean luminance.
    write_png(mitsuba, np.abs(relight_image - mitsuba_image) / scale, absolute_path)
    # Signed block-averaged difference on the lit surfaces (emitters blacked
    # out), where systematic errors show as coherent red or blue regions.
    masked_relight = relight_image * surface_mask[..., None]
    masked_mitsuba = mitsuba_image * surface_mask[..., None]
    block_difference = luminance(block_average(masked_relight, block)) - luminance(block_average(masked_mitsuba, block))
    false_colour = signed_false_colour(block_difference, 0.1 * scale)
    false_colour = np.repeat(np.repeat(false_colour, block, axis=0), block, axis=1)
    blocks_path = output_directory / "difference_blocks.png"
    write_png(mitsuba, false_colour, blocks_path)
    return [absolute_path, blocks_path]


def format_rgb(image: np.ndarray) -> str:
    mean = image.reshape(-1, 3).mean(axis=0)
    return f"({mean[0]:.5f}, {mean[1]:.5f}, {mean[2]:.5f})"


def parse_arguments(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=(
            "Render an OBJ scene with relight's reference path tracer and with Mitsuba 3 "
            "(scalar_rgb) and compare the images by relative RMSE against a bound derived "
            "from the measured Monte Carlo noise. Exit 0 = agree, 1 = disagree, 2 = usage/input error."
        ),
        epilog="Three comparisons must each stay within their bound: the full image; the lit surfaces "
        "(pixels that see an emitter directly masked out); the lit surfaces averaged over BLOCK x BLOCK "
        "tiles. Each bound is noise_floor * %.1f + %.2f, where noise_floor is the relRMSE expected from "
        "Monte Carlo noise alone, measured from two renders of each renderer with different seeds; see "
        "the module docstring." % (NOISE_FACTOR, SYSTEMATIC_ALLOWANCE),
    )
    parser.add_argument("scene", type=Path, help="relight scene file (TOML) whose mesh is an OBJ/MTL file")
    parser.add_argument(
        "--relight", metavar="PATH",
        help="relight CLI binary (default: target/release/relight, then target/debug/relight, then PATH)",
    )
    parser.add_argument(
        "--relight-image", metavar="EXR", type=Path,
        help="compare this existing relight EXR instead of running relight (it must have been rendered "
        "with the same --spp and --max-bounces)",
    )
    parser.add_argument("--spp", type=int, default=DEFAULT_SPP, help=f"samples per pixel for both renderers (default {DEFAULT_SPP})")
    parser.add_argument(
        "--max-bounces", type=int, default=DEFAULT_MAX_BOUNCES,
        help=f"relight's bounce count, 0 = direct light only (default {DEFAULT_MAX_BOUNCES}); Mitsuba gets max_depth = this + 2",
    )
    parser.add_argument("--out", type=Path, default=REPOSITORY_ROOT / "out" / "cross-check", help="output directory for images (default out/cross-check)")
    parser.add_argument("--bound", type=float, help="override the full-image relRMSE bound")
    parser.add_argument("--surface-bound", type=float, help="override the lit-surfaces relRMSE bound")
    parser.add_argument("--block-bound", type=float, help="override the block-averaged lit-surfaces relRMSE bound")
    parser.add_argument(
        "--block", type=int, default=DEFAULT_BLOCK,
        help=f"tile size in pixels for the block-averaged comparison (default {DEFAULT_BLOCK})",
    )
    arguments = parser.parse_args(argv)
    if arguments.spp < 1:
        parser.error("--spp must be at least 1")
    if arguments.max_bounces < 0:
        parser.error("--max-bounces must be non-negative")
    if arguments.block < 1:
        parser.error("--block must be at least 1")
    for name in ("bound", "surface_bound", "block_bound"):
        value = getattr(arguments, name)
        if value is not None and not value > 0.0:
            parser.error(f"--{name.replace('_', '-')} must be positive")
    return arguments


@dataclass
class Comparison:
    """relRMSE of relight against Mitsuba on one view of the images, with its noise floor and bound."""
    label: str
    noise_floor: float
    bound: float
    bound_source: str
    error: float

    @property
    def passed(self) -> bool:
        return self.error <= self.bound


def expected_noise_relative_rmse(mitsuba_pair, relight_pair) -> float:
    """Pure-noise relRMSE expected between one relight and one Mitsuba render.

    E|R - M|^2 = Var_R + Var_M, and two renders of one renderer with different
    seeds have E|X1 - X2|^2 = 2 Var_X, so the expected squared relRMSE of
    relight against Mitsuba is the mean of the two within-renderer squared
    relRMSEs. Without a second relight render, relight's variance is taken to
    equal Mitsuba's.
    """
    mitsuba_noise = relative_rmse(mitsuba_pair[1], mitsuba_pair[0])
    if relight_pair is None:
        return mitsuba_noise
    relight_noise = relative_rmse(relight_pair[1], relight_pair[0])
    return math.sqrt(0.5 * (mitsuba_noise**2 + relight_noise**2))


def compare(label, relight_images, mitsuba_images, given_bound, has_relight_pair) -> Comparison:
    noise_floor = expected_noise_relative_rmse(mitsuba_images, relight_images if has_relight_pair else None)
    if given_bound is not None:
        bound, bound_source = given_bound, "given"
    else:
        bound = noise_floor * NOISE_FACTOR + SYSTEMATIC_ALLOWANCE
        bound_source = f"noise * {NOISE_FACTOR} + {SYSTEMATIC_ALLOWANCE}"
    return Comparison(
        label=label,
        noise_floor=noise_floor,
        bound=bound,
        bound_source=bound_source,
        error=relative_rmse(relight_images[0], mitsuba_images[0]),
    )


def load_relight_images(
    mitsuba, arguments, relight_binary: str | None, scene: SceneDescription, output_directory: Path
) -> list[np.ndarray]:
    """relight's render(s): two seeds normally, one when --relight-image is given."""
    if arguments.relight_image is not None:
        paths = [arguments.relight_image]
    else:
        paths = []
        for seed in RELIGHT_SEEDS:
            path = output_directory / ("relight.exr" if seed == RELIGHT_SEEDS[0] else f"relight_seed{seed}.exr")
            run_relight(relight_binary, arguments.scene, arguments.spp, arguments.max_bounces, seed, path)
            paths.append(path)
    images = []
    camera = scene.camera
    for path in paths:
        image = read_exr_rgb(mitsuba, path)
        if image.shape[:2] != (camera.height, camera.width):
            raise InputError(
                f"relight image {path} is {image.shape[1]}x{image.shape[0]}, "
                f"the scene asks for {camera.width}x{camera.height}"
            )
        images.append(image)
    return images


def cross_check(arguments: argparse.Namespace) -> int:
    started = time.monotonic()
    scene = read_scene_file(arguments.scene)
    for warning in scene.warnings:
        print(f"warning: {warning}", file=sys.stderr)
    mitsuba = import_mitsuba()
    relight_binary = None if arguments.relight_image is not None else find_relight_binary(arguments.relight)
    output_directory = arguments.out
    output_directory.mkdir(parents=True, exist_ok=True)
    camera = scene.camera
    block = arguments.block
    if block > min(camera.width, camera.height):
        raise InputError(f"--block {block} is larger than the image")
    print(
        f"scene {scene.source}: {camera.width}x{camera.height}, "
        f"{sum(len(triangles) for triangles in scene.triangles_by_material.values())} triangles, "
        f"{len(scene.triangles_by_material)} materials, {len(scene.lights)} lights; "
        f"spp {arguments.spp}, max bounces {arguments.max_bounces} "
        f"(Mitsuba max_depth {mitsuba_max_depth(arguments.max_bounces)})",
        flush=True,
    )

    stage_started = time.monotonic()
    relight_images = load_relight_images(mitsuba, arguments, relight_binary, scene, output_directory)
    relight_seconds = time.monotonic() - stage_started
    if not all(np.all(np.isfinite(image)) for image in relight_images):
        print("FAIL: relight's image contains non-finite pixels", file=sys.stderr)
        return 1

    stage_started = time.monotonic()
    mitsuba_scene = build_mitsuba_scene(mitsuba, scene, arguments.spp, mitsuba_max_depth(arguments.max_bounces))
    mitsuba_images = [render_mitsuba(mitsuba, mitsuba_scene, arguments.spp, seed) for seed in MITSUBA_SEEDS]
    surface_mask = ~emitter_mask(mitsuba, scene)
    mitsuba_seconds = time.monotonic() - stage_started

    write_exr(mitsuba, mitsuba_images[0], output_directory / "mitsuba.exr")
    write_exr(mitsuba, mitsuba_images[1], output_directory / f"mitsuba_seed{MITSUBA_SEEDS[1]}.exr")
    write_png(mitsuba, mitsuba_images[0], output_directory / "mitsuba.png")
    write_png(mitsuba, relight_images[0], output_directory / "relight.png")
    difference_paths = write_difference_images(
        mitsuba, relight_images[0], mitsuba_images[0], surface_mask, block, output_directory
    )

    has_relight_pair = len(relight_images) == 2
    relight_surfaces = [image * surface_mask[..., None] for image in relight_images]
    mitsuba_surfaces = [image * surface_mask[..., None] for image in mitsuba_images]
    comparisons = [
        compare("full image", relight_images, mitsuba_images, arguments.bound, has_relight_pair),
        compare("lit surfaces", relight_surfaces, mitsuba_surfaces, arguments.surface_bound, has_relight_pair),
        compare(
            f"surfaces {block}x{block}",
            [block_average(image, block) for image in relight_surfaces],
            [block_average(image, block) for image in mitsuba_surfaces],
            arguments.block_bound,
            has_relight_pair,
        ),
    ]
    passed = all(comparison.passed for comparison in comparisons)

    relight_mean = relight_images[0].reshape(-1, 3).mean(axis=0)
    mitsuba_mean = mitsuba_images[0].reshape(-1, 3).mean(axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        mean_ratio = relight_mean / mitsuba_mean
    print(f"relight mean RGB  {format_rgb(relight_images[0])}   ({relight_seconds:.1f} s for {len(relight_images)} render(s))")
    print(f"Mitsuba mean RGB  {format_rgb(mitsuba_images[0])}   ({mitsuba_seconds:.1f} s for 2 renders)")
    print(f"mean ratio relight/Mitsuba  ({mean_ratio[0]:.4f}, {mean_ratio[1]:.4f}, {mean_ratio[2]:.4f})")
    noise_source = (
        "noise floor = expected relRMSE of independent renders, from relight's and Mitsuba's seed pairs"
        if has_relight_pair
        else "noise floor = relRMSE of Mitsuba's seed pair (relight's variance assumed equal)"
    )
    print(noise_source)
    masked_count = int(surface_mask.size - surface_mask.sum())
    print(f"lit surfaces = all pixels but the {masked_count} that see emission directly (dilated by 1 pixel)")
    for comparison in comparisons:
        print(
            f"{comparison.label:>14}: noise floor {comparison.noise_floor:.4f}  bound {comparison.bound:.4f} "
            f"({comparison.bound_source})  relRMSE {comparison.error:.4f}  "
            f"{'ok' if comparison.passed else 'ABOVE BOUND'}"
        )
    print(f"images in {output_directory}: relight.exr, mitsuba.exr, " + ", ".join(path.name for path in difference_paths))
    print(
        f"{'PASS' if passed else 'FAIL'}: relight {'agrees' if passed else 'disagrees'} with Mitsuba "
        f"(total {time.monotonic() - started:.1f} s)"
    )
    return 0 if passed else 1


def main(argv: list[str] | None = None) -> int:
    arguments = parse_arguments(sys.argv[1:] if argv is None else argv)
    try:
        return cross_check(arguments)
    except InputError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
