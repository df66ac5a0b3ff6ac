//! Telling a frame that would repeat the last update, so that an update
//! whose inputs have not changed costs nothing.

use crate::Frame;
use glam::Affine3A;
use relight_scene::{Camera, Light};

/// Which parts of a [`Frame`] a technique's update reads, besides the
/// lights, which every update reads.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FrameReads {
    /// The camera: view-dependent (glossy) light computed in the update.
    pub camera: bool,
    /// The moving meshes' poses, and the frame index when a frame gives
    /// none (their scripted motion follows the index).
    pub moving_meshes: bool,
}

/// What the last update read from its frame.
///
/// A technique asks [`LastFrame::repeats`] at the top of each update; when
/// the frame repeats the last one and the technique's light is settled
/// (another update would leave it where it is), the update is skipped and
/// [`crate::StageTimings::skipped`] says so. An engine may then call `update`
/// every frame, whether or not anything moved, and pay for the frames in
/// which something did.
#[derive(Clone, Debug, Default)]
pub struct LastFrame {
    known: bool,
    lights: Vec<Light>,
    camera: Option<Camera>,
    poses: Option<Vec<Affine3A>>,
    index: u64,
}

impl LastFrame {
    /// Whether `frame` gives an update that reads `reads` the same inputs
    /// as the last frame given here; records `frame` either way.
    pub fn repeats(&mut self, frame: &Frame, reads: FrameReads) -> bool {
        let same = self.known
            && self.lights.as_slice() == frame.lights
            && (!reads.camera || self.camera.as_ref() == frame.camera)
            && (!reads.moving_meshes
                || (self.poses.as_deref() == frame.moving_mesh_poses
                    && (frame.moving_mesh_poses.is_some() || self.index == frame.index)));
        if !same {
            self.known = true;
            self.lights.clear();
            self.lights.extend_from_slice(frame.lights);
            self.camera = frame.camera.cloned();
            match (&mut self.poses, frame.moving_mesh_poses) {
                (Some(poses), Some(new)) => {
                    poses.clear();
                    poses.extend_from_slice(new);
                }
                (poses, new) => *poses = new.map(<[Affine3A]>::to_vec),
            }
        }
        self.index = frame.index;
        same
    }

    /// Forgets the last frame, so the next update runs whatever it is
    /// given (after an update that failed part way).
    pub fn forget(&mut self) {
        self.known = false;
    }
}
