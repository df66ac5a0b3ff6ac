//! Captured point clouds as extra VALs (section 5): a PLY file (ASCII or
//! binary, either byte order) whose `vertex` element has x, y, z, nx, ny,
//! nz and red, green, blue (8-bit or floating point, sRGB-encoded), as an
//! RGB-D camera's points come. Each point is a Lambertian disc whose
//! radiance is its linear colour times `scale`; its area is a `radius`
//! property when present, otherwise pi d^2 / 7 with d the distance to its
//! eighth nearest facing neighbour (itself included): the area per point of
//! the local sampling density.

use crate::points::{Nearest, PointGrid, NEIGHBOURS};
use crate::vals::Val;
use crate::LightSkinError;
use glam::Vec3;
use relight_core::colour::srgb_to_linear;
use relight_core::Rgb;
use std::path::Path;

/// Most points accepted: a point cloud larger than this is a mistake or an
/// attack on memory, and would take seconds per frame to gather anyway.
pub const MAX_POINTS: usize = 4_000_000;

#[derive(Clone, Copy, Debug, PartialEq)]
enum Format {
    Ascii,
    BinaryLittle,
    BinaryBig,
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Scalar {
    fn parse(name: &str) -> Option<Scalar> {
        Some(match name {
            "char" | "int8" => Scalar::I8,
            "uchar" | "uint8" => Scalar::U8,
            "short" | "int16" => Scalar::I16,
            "ushort" | "uint16" => Scalar::U16,
            "int" | "int32" => Scalar::I32,
            "uint" | "uint32" => Scalar::U32,
            "float" | "float32" => Scalar::F32,
            "double" | "float64" => Scalar::F64,
            _ => return None,
        })
    }

    fn size(self) -> usize {
        match self {
            Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::F64 => 8,
        }
    }

    fn read(self, bytes: &[u8], format: Format) -> f64 {
        macro_rules! decode {
            ($t:ty) => {{
                let array = bytes.try_into().expect("sized by Scalar::size");
                (if format == Format::BinaryBig {
                    <$t>::from_be_bytes(array)
                } else {
                    <$t>::from_le_bytes(array)
                }) as f64
            }};
        }
        match self {
            Scalar::I8 => bytes[0] as i8 as f64,
            Scalar::U8 => bytes[0] as f64,
            Scalar::I16 => decode!(i16),
            Scalar::U16 => decode!(u16),
            Scalar::I32 => decode!(i32),
            Scalar::U32 => decode!(u32),
            Scalar::F32 => decode!(f32),
            Scalar::F64 => decode!(f64),
        }
    }
}

struct Element {
    name: String,
    count: usize,
    /// (name, type); `None` type marks a list property.
    properties: Vec<(String, Option<Scalar>)>,
}

/// One captured point.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CloudPoint {
    pub position: Vec3,
    pub normal: Vec3,
    /// Linear colour.
    pub colour: Rgb,
    pub radius: Option<f32>,
}

fn error(path: &Path, message: impl Into<String>) -> LightSkinError {
    LightSkinError::PointCloud {
        path: path.to_path_buf(),
        message: message.into(),
    }
}

/// Reads the points of a PLY file.
pub fn read_point_cloud(path: &Path) -> Result<Vec<CloudPoint>, LightSkinError> {
    let bytes = std::fs::read(path).map_err(|e| {
        error(
            path,
            format!("cannot read the point cloud ({e}); check the `point_cloud` parameter"),
        )
    })?;
    parse_point_cloud(path, &bytes)
}

/// Parses PLY bytes (`path` only names the file in messages).
pub fn parse_point_cloud(path: &Path, bytes: &[u8]) -> Result<Vec<CloudPoint>, LightSkinError> {
    // The header is ASCII lines up to and including "end_header".
    let mut offset = 0;
    let mut lines = Vec::new();
    loop {
        let Some(end) = bytes[offset..].iter().position(|&b| b == b'\n') else {
            return Err(error(path, "the PLY header has no `end_header` line"));
        };
        let line = String::from_utf8_lossy(&bytes[offset..offset + end])
            .trim()
            .to_string();
        offset += end + 1;
        let done = line == "end_header";
        lines.push(line);
        if done {
            break;
        }
        if lines.len() > 10_000 {
            return Err(error(path, "the PLY header is longer than 10000 lines"));
        }
    }
    if lines.first().map(String::as_str) != Some("ply") {
        return Err(error(
            path,
            "line 1: not a PLY file (it must start with `ply`)",
        ));
    }
    let mut format = None;
    let mut elements: Vec<Element> = Vec::new();
    for (number, line) in lines.iter().enumerate().skip(1) {
        let line_number = number + 1;
        let words: Vec<&str> = line.split_whitespace().collect();
        match words.as_slice() {
            ["format", kind, _version] => {
                format = Some(match *kind {
                    "ascii" => Format::Ascii,
                    "binary_little_endian" => Format::BinaryLittle,
                    "binary_big_endian" => Format::BinaryBig,
                    other => {
                        return Err(error(
                            path,
                            format!("line {line_number}: unknown PLY format `{other}`"),
                        ))
                    }
                })
            }
            ["element", name, count] => {
                let count: usize = count.parse().map_err(|_| {
                    error(
                        path,
                        format!("line {line_number}: element count `{count}` is not a number"),
                    )
                })?;
                elements.push(Element {
                    name: name.to_string(),
                    count,
                    properties: Vec::new(),
                });
            }
            ["property", "list", ..] => {
                let Some(element) = elements.last_mut() else {
                    return Err(error(
                        path,
                        format!("line {line_number}: property before any element"),
                    ));
                };
                element
                    .properties
                    .push((words.last().unwrap_or(&"").to_string(), None));
            }
            ["property", kind, name] => {
                let Some(element) = elements.last_mut() else {
                    return Err(error(
                        path,
                        format!("line {line_number}: property before any element"),
                    ));
                };
                let scalar = Scalar::parse(kind).ok_or_else(|| {
                    error(
                        path,
                        format!("line {line_number}: unknown property type `{kind}`"),
                    )
                })?;
                element.properties.push((name.to_string(), Some(scalar)));
            }
            ["comment", ..] | ["obj_info", ..] | ["end_header"] | [] => {}
            _ => {
                return Err(error(
                    path,
                    format!("line {line_number}: cannot read `{line}` in the PLY header"),
                ))
            }
        }
    }
    let format = format.ok_or_else(|| error(path, "the PLY header has no `format` line"))?;
    let Some(vertex_index) = elements.iter().position(|e| e.name == "vertex") else {
        return Err(error(path, "the PLY file has no `vertex` element"));
    };
    let vertex = &elements[vertex_index];
    if vertex.count > MAX_POINTS {
        return Err(error(
            path,
            format!(
                "{} points is more than the {MAX_POINTS} accepted; subsample the capture",
                vertex.count
            ),
        ));
    }
    if vertex.properties.iter().any(|(_, kind)| kind.is_none()) {
        return Err(error(
            path,
            "the `vertex` element has a list property; store points with scalar properties only",
        ));
    }
    let column = |name: &str| vertex.properties.iter().position(|(n, _)| n == name);
    let required = |name: &str| {
        column(name).ok_or_else(|| {
            error(
                path,
                format!("the `vertex` element has no `{name}` property; points need x, y, z, nx, ny, nz, red, green, blue"),
            )
        })
    };
    let positions = [required("x")?, required("y")?, required("z")?];
    let normals = [required("nx")?, required("ny")?, required("nz")?];
    let colours = [required("red")?, required("green")?, required("blue")?];
    let radius = column("radius");
    let colour_scale: Vec<f64> = colours
        .iter()
        .map(|&c| match vertex.properties[c].1 {
            Some(Scalar::U8) => 1.0 / 255.0,
            Some(Scalar::U16) => 1.0 / 65535.0,
            _ => 1.0,
        })
        .collect();

    let mut values = vec![0.0f64; vertex.properties.len()];
    let mut points = Vec::with_capacity(vertex.count);
    let mut build = |values: &[f64], index: usize| -> Result<(), LightSkinError> {
        let position = Vec3::new(
            values[positions[0]] as f32,
            values[positions[1]] as f32,
            values[positions[2]] as f32,
        );
        let normal = Vec3::new(
            values[normals[0]] as f32,
            values[normals[1]] as f32,
            values[normals[2]] as f32,
        );
        let colour = Rgb::new(
            srgb_to_linear((values[colours[0]] * colour_scale[0]).clamp(0.0, 1.0) as f32),
            srgb_to_linear((values[colours[1]] * colour_scale[1]).clamp(0.0, 1.0) as f32),
            srgb_to_linear((values[colours[2]] * colour_scale[2]).clamp(0.0, 1.0) as f32),
        );
        let radius = radius.map(|r| values[r] as f32);
        if !position.is_finite()
            || !normal.is_finite()
            || radius.is_some_and(|r| !(r.is_finite() && r >= 0.0))
        {
            return Err(error(
                path,
                format!("point {index} has a non-finite position, normal or radius"),
            ));
        }
        let Some(normal) = normal.try_normalize() else {
            return Err(error(
                path,
                format!("point {index} has a zero normal; estimate normals before loading"),
            ));
        };
        points.push(CloudPoint {
            position,
            normal,
            colour,
            radius,
        });
        Ok(())
    };
    let body = &bytes[offset..];
    match format {
        Format::Ascii => {
            let text = String::from_utf8_lossy(body);
            let mut rows = text.lines().filter(|l| !l.trim().is_empty());
            for element in &elements[..vertex_index] {
                for _ in 0..element.count {
                    rows.next();
                }
            }
            for index in 0..vertex.count {
                let row = rows.next().ok_or_else(|| {
                    error(
                        path,
                        format!("the file ends after {index} of {} points", vertex.count),
                    )
                })?;
                let mut fields = row.split_whitespace();
                for (slot, value) in values.iter_mut().enumerate() {
                    let field = fields.next().ok_or_else(|| {
                        error(
                            path,
                            format!(
                                "point {index} has fewer than {} values",
                                vertex.properties.len()
                            ),
                        )
                    })?;
                    *value = field.parse().map_err(|_| {
                        error(
                            path,
                            format!(
                                "point {index}, property {}: `{field}` is not a number",
                                vertex.properties[slot].0
                            ),
                        )
                    })?;
                }
                build(&values, index)?;
            }
        }
        Format::BinaryLittle | Format::BinaryBig => {
            let mut cursor = 0usize;
            for element in &elements[..vertex_index] {
                if element.properties.iter().any(|(_, kind)| kind.is_none()) {
                    return Err(error(path, format!("element `{}` before `vertex` has list properties; write `vertex` first", element.name)));
                }
                let stride: usize = element
                    .properties
                    .iter()
                    .map(|(_, k)| k.map_or(0, Scalar::size))
                    .sum();
                cursor = element
                    .count
                    .checked_mul(stride)
                    .and_then(|size| cursor.checked_add(size))
                    .ok_or_else(|| error(path, "element sizes overflow"))?;
            }
            let types: Vec<Scalar> = vertex.properties.iter().filter_map(|(_, k)| *k).collect();
            let stride: usize = types.iter().map(|t| t.size()).sum();
            let needed = vertex
                .count
                .checked_mul(stride)
                .and_then(|size| size.checked_add(cursor))
                .ok_or_else(|| error(path, "element sizes overflow"))?;
            if body.len() < needed {
                return Err(error(
                    path,
                    format!("the file holds {} bytes of point data but the header needs {needed}: it is truncated", body.len()),
                ));
            }
            for index in 0..vertex.count {
                for (value, kind) in values.iter_mut().zip(&types) {
                    *value = kind.read(&body[cursor..cursor + kind.size()], format);
                    cursor += kind.size();
                }
                build(&values, index)?;
            }
        }
    }
    Ok(points)
}

/// VALs for captured points: radiance = colour * scale, so the power over
/// pi of a disc of area A is colour * scale * A.
pub fn point_cloud_vals(points: &[CloudPoint], scale: f32) -> Vec<Val> {
    let positions: Vec<Vec3> = points.iter().map(|p| p.position).collect();
    let normals: Vec<Vec3> = points.iter().map(|p| p.normal).collect();
    let needs_density = points.iter().any(|p| p.radius.is_none());
    let (low, high) = positions.iter().fold(
        (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
        |(l, h), &p| (l.min(p), h.max(p)),
    );
    let cell = if points.is_empty() {
        1.0
    } else {
        // About a few points per cell for a surface-like cloud.
        let extent = (high - low).max_element().max(1e-6);
        extent / (points.len() as f32).sqrt().max(1.0) * 2.0
    };
    let grid = needs_density.then(|| PointGrid::new(&positions, cell));
    let mut found = Nearest::default();
    points
        .iter()
        .map(|point| {
            let area = match (point.radius, &grid) {
                (Some(radius), _) => std::f32::consts::PI * radius * radius,
                (None, Some(grid)) => {
                    grid.nearest_facing(point.position, point.normal, &normals, &mut found);
                    let farthest = found.as_slice().last().map_or(0.0, |&(_, d)| d);
                    std::f32::consts::PI * farthest * farthest / (NEIGHBOURS as f32 - 1.0)
                }
                (None, None) => 0.0,
            };
            Val {
                position: point.position,
                normal: point.normal,
                power_over_pi: point.colour * (scale * area),
                area: area.max(1e-12),
            }
        })
        .collect()
}

/// Reads a PLY point cloud and turns it into VALs.
pub fn read_point_cloud_vals(path: &Path, scale: f32) -> Result<Vec<Val>, LightSkinError> {
    Ok(point_cloud_vals(&read_point_cloud(path)?, scale))
}
