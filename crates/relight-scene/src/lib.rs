//! The static scene every relight technique works on, how it is read from
//! disk, and its lightmap atlas.
//!
//! Data flow: a `scene.toml` names a mesh (OBJ+MTL or glTF) and adds a camera,
//! lights and an environment; [`load_scene`] turns all of it into one
//! [`Scene`] (triangles, Lambertian materials, textures, lights). The
//! [`atlas`] module then parameterises the static geometry for lightmaps and
//! produces the [`atlas::Receivers`] (lightmap texels that cover geometry)
//! on which every technique stores, and is measured on, indirect light;
//! [`detail`] decides where the atlas spends its texels (full density where
//! the scene's detail is, coarser outside), cutting at load the few huge
//! triangles that reach far out, such as a ground plane; [`seams`] cuts
//! surfaces along the feet of the walls that stand on them, so that the
//! atlas's charts end there.
//! Lights are the only part of a scene that changes from frame to frame.

pub mod atlas;
pub mod detail;
mod error;
pub mod generate;
mod gltf_loader;
mod mesh_input;
mod model;
mod obj_loader;
mod scene_file;
pub mod seams;

pub use error::SceneError;
pub use model::*;
pub use scene_file::{
    is_mesh_file, load_mesh, load_scene, parse_scene_file, SceneFile, TECHNIQUE_SECTIONS,
};
