//! Orbit camera and perspective projection of world points into the 3D view's screen rectangle.
//!
//! The eye sits on a sphere of radius `distance_m` around `target_m`, placed by yaw (about the
//! world z axis, which is up) and pitch (elevation). `Projector` combines glam's right-handed
//! look-at and (Y-up, depth 0..1) perspective matrices into `clip_from_world` and maps normalised device
//! coordinates into the egui rectangle; the painter then draws 2D shapes at those positions.
//! A point at or behind the near plane does not project.

use egui::{Pos2, Rect, Vec2};
use glam::{Mat4, Vec3, Vec4};

/// Near and far clip distances, metres.
const NEAR_M: f32 = 0.01;
const FAR_M: f32 = 100.0;
/// Pitch stays short of the poles, where the look-at basis degenerates.
const MAX_PITCH_RAD: f32 = 1.5;

/// An orbit camera: drag rotates, scroll zooms, secondary drag pans.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OrbitCamera {
    pub target_m: Vec3,
    pub distance_m: f32,
    /// Rotation about world z, radians (0: eye on +x looking towards -x).
    pub yaw_rad: f32,
    /// Elevation above the xy plane, radians.
    pub pitch_rad: f32,
    /// Vertical field of view, radians.
    pub fov_y_rad: f32,
}

impl Default for OrbitCamera {
    fn default() -> Self {
        Self {
            target_m: Vec3::ZERO,
            distance_m: 0.5,
            yaw_rad: 0.6,
            pitch_rad: 0.4,
            fov_y_rad: 45f32.to_radians(),
        }
    }
}

impl OrbitCamera {
    /// A camera looking at `target_m` from direction `from_dir` (target to eye), at `distance_m`.
    pub fn looking_from(target_m: Vec3, from_dir: Vec3, distance_m: f32) -> Self {
        let d = from_dir.normalize_or(Vec3::X);
        Self {
            target_m,
            distance_m,
            yaw_rad: d.y.atan2(d.x),
            pitch_rad: d
                .z
                .clamp(-1.0, 1.0)
                .asin()
                .clamp(-MAX_PITCH_RAD, MAX_PITCH_RAD),
            ..Self::default()
        }
    }

    /// Unit vector from the target to the eye.
    pub fn eye_dir(&self) -> Vec3 {
        let (sy, cy) = self.yaw_rad.sin_cos();
        let (sp, cp) = self.pitch_rad.sin_cos();
        Vec3::new(cp * cy, cp * sy, sp)
    }

    pub fn eye_m(&self) -> Vec3 {
        self.target_m + self.distance_m * self.eye_dir()
    }

    /// Rotate by a mouse drag of `delta_px` (right drags the scene to the right).
    pub fn rotate(&mut self, delta_px: Vec2) {
        const RAD_PER_PX: f32 = 0.008;
        self.yaw_rad -= delta_px.x * RAD_PER_PX;
        self.pitch_rad =
            (self.pitch_rad + delta_px.y * RAD_PER_PX).clamp(-MAX_PITCH_RAD, MAX_PITCH_RAD);
    }

    /// Zoom by a scroll of `scroll_px` (positive scrolls in).
    pub fn zoom(&mut self, scroll_px: f32) {
        self.distance_m =
            (self.distance_m * (-scroll_px * 0.002).exp()).clamp(2.0 * NEAR_M, 0.5 * FAR_M);
    }

    /// Move the target in the view plane by a drag of `delta_px` in a view `height_px` tall.
    pub fn pan(&mut self, delta_px: Vec2, height_px: f32) {
        let m_per_px = 2.0 * self.distance_m * (0.5 * self.fov_y_rad).tan() / height_px.max(1.0);
        let forward = -self.eye_dir();
        let right = forward.cross(Vec3::Z).normalize_or(Vec3::Y);
        let up = right.cross(forward);
        self.target_m += (-delta_px.x * right + delta_px.y * up) * m_per_px;
    }

    /// The projector for a view drawn into `rect`.
    pub fn projector(&self, rect: Rect) -> Projector {
        let aspect = rect.width().max(1.0) / rect.height().max(1.0);
        let view_from_world =
            glam::camera::rh::view::look_at_mat4(self.eye_m(), self.target_m, Vec3::Z);
        let clip_from_view =
            glam::camera::rh::proj::directx::perspective(self.fov_y_rad, aspect, NEAR_M, FAR_M);
        Projector {
            clip_from_world: clip_from_view * view_from_world,
            view_from_world,
            rect,
            focal_px: 0.5 * rect.height() / (0.5 * self.fov_y_rad).tan(),
        }
    }
}

/// World-to-screen mapping of one frame of the 3D view.
#[derive(Clone, Copy, Debug)]
pub struct Projector {
    clip_from_world: Mat4,
    view_from_world: Mat4,
    rect: Rect,
    /// Focal length in pixels (screen size of 1 m at 1 m depth).
    focal_px: f32,
}

impl Projector {
    /// Screen position and view depth (metres in front of the eye) of a world point, or `None`
    /// when it lies at or behind the near plane or is not finite.
    pub fn project(&self, p_m: Vec3) -> Option<(Pos2, f32)> {
        if !p_m.is_finite() {
            return None;
        }
        let depth = -(self.view_from_world * p_m.extend(1.0)).z;
        if depth <= NEAR_M {
            return None;
        }
        let clip: Vec4 = self.clip_from_world * p_m.extend(1.0);
        let ndc = clip.truncate() / clip.w;
        let pos = Pos2::new(
            self.rect.center().x + 0.5 * ndc.x * self.rect.width(),
            self.rect.center().y - 0.5 * ndc.y * self.rect.height(),
        );
        Some((pos, depth))
    }

    /// Screen radius of a sphere of `radius_m` whose centre is `depth_m` in front of the eye.
    pub fn radius_px(&self, radius_m: f32, depth_m: f32) -> f32 {
        radius_m * self.focal_px / depth_m.max(NEAR_M)
    }

    pub fn rect(&self) -> Rect {
        self.rect
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn rect() -> Rect {
        Rect::from_min_size(Pos2::new(10.0, 20.0), Vec2::new(400.0, 300.0))
    }

    #[test]
    fn target_projects_to_the_centre() {
        let cam =
            OrbitCamera::looking_from(Vec3::new(0.3, -0.2, 1.0), Vec3::new(1.0, 2.0, 0.5), 0.7);
        let (pos, depth) = cam.projector(rect()).project(cam.target_m).unwrap();
        assert!((pos - rect().center()).length() < 1e-3);
        assert!((depth - 0.7).abs() < 1e-5);
    }

    #[test]
    fn up_is_up_on_screen_and_behind_is_culled() {
        let cam = OrbitCamera::looking_from(Vec3::ZERO, Vec3::X, 1.0);
        let p = cam.projector(rect());
        let (above, _) = p.project(Vec3::new(0.0, 0.0, 0.1)).unwrap();
        assert!(above.y < rect().center().y);
        // Looking from +x towards -x with z up: +y is to the right... of a right-handed view.
        let (right, _) = p.project(Vec3::new(0.0, 0.1, 0.0)).unwrap();
        assert!(right.x > rect().center().x);
        assert!(p.project(Vec3::new(2.0, 0.0, 0.0)).is_none());
        assert!(p.project(Vec3::NAN).is_none());
    }

    #[test]
    fn sphere_radius_matches_projected_offset() {
        let cam = OrbitCamera::looking_from(Vec3::ZERO, Vec3::new(0.0, -1.0, 0.0), 0.5);
        let p = cam.projector(rect());
        let (c, depth) = p.project(Vec3::ZERO).unwrap();
        let (edge, _) = p.project(Vec3::new(0.0, 0.0, 0.01)).unwrap();
        assert!(((c - edge).length() - p.radius_px(0.01, depth)).abs() < 0.05);
    }

    proptest! {
        #[test]
        fn orbit_keeps_distance_and_target_centred(yaw in -10.0f32..10.0, pitch in -3.0f32..3.0,
                                                   dx in -500.0f32..500.0, dy in -500.0f32..500.0,
                                                   scroll in -400.0f32..400.0) {
            let mut cam = OrbitCamera { yaw_rad: yaw, pitch_rad: pitch.clamp(-1.5, 1.5), ..OrbitCamera::default() };
            cam.rotate(Vec2::new(dx, dy));
            cam.zoom(scroll);
            prop_assert!(cam.pitch_rad.abs() <= MAX_PITCH_RAD);
            prop_assert!(((cam.eye_m() - cam.target_m).length() - cam.distance_m).abs() < 1e-4);
            let (pos, _) = cam.projector(rect()).project(cam.target_m).unwrap();
            prop_assert!((pos - rect().center()).length() < 1e-2);
        }

        #[test]
        fn pan_moves_target_perpendicular_to_view(dx in -300.0f32..300.0, dy in -300.0f32..300.0) {
            let mut cam = OrbitCamera::default();
            let before = cam.target_m;
            cam.pan(Vec2::new(dx, dy), 300.0);
            prop_assert!((cam.target_m - before).dot(cam.eye_dir()).abs() < 1e-5);
        }
    }
}
