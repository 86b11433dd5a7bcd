//! Paints one [`ViewFrame`] in 3D with egui's painter: every world-space element is projected
//! by the orbit camera's [`Projector`] and drawn as 2D shapes (painter's algorithm: context
//! first, estimates on top; the surface patch is depth-sorted back to front).
//!
//! What is drawn follows paper Fig. 4 and Fig. 7: point layers by role (rejected points red,
//! clustered-out orange, kept grey-blue, memorised green), the HIP sphere, the concentric shell
//! spheres (their silhouettes), each shell's fit (plane disc with its red normal for the
//! innermost shell, fitted circles with their normals for the others; rejected fits dashed,
//! grey and crossed out), each camera's estimate (grey and crossed out when the camera
//! rejected it), the fused surface (blue normal), the ground truth (magenta) and the HIP's
//! projection on the fused surface plane; the HIP sphere takes the colour of the haptic
//! constraint state ([`hip_color`]). The returned [`DrawStats`] count what was actually drawn.

use super::frame::{GuardView, PointRole, ViewFrame};
use super::orbit::{OrbitCamera, Projector};
use super::patch::SurfacePatch;
use crate::haptics::HapticStatus;
use crate::surface::SurfacePoint;
use crate::surface::{ShellFit, ShellFitKind};
use egui::{Color32, Mesh, Painter, Pos2, Shape, Stroke, Vec2};
use glam::Vec3;
use nalgebra::{Point3, Vector3};
use std::collections::BTreeMap;

/// Colour of a point role.
pub fn role_color(role: PointRole) -> Color32 {
    match role {
        PointRole::Kept => Color32::from_rgb(150, 165, 200),
        PointRole::Cropped => Color32::from_rgb(200, 60, 60),
        PointRole::ClusteredOut => Color32::from_rgb(235, 150, 40),
        PointRole::Memorised => Color32::from_rgb(60, 200, 90),
    }
}

pub const HIP_COLOR: Color32 = Color32::from_rgb(240, 210, 60);
/// HIP sphere while the haptic constraints are in force.
pub const HIP_ACTIVE_COLOR: Color32 = Color32::from_rgb(245, 140, 40);
/// HIP sphere while the motion reaches a constraint's bound.
pub const HIP_BINDING_COLOR: Color32 = Color32::from_rgb(235, 50, 50);
/// HIP sphere while no tracking surface exists (constraints off).
pub const HIP_NO_SURFACE_COLOR: Color32 = Color32::from_rgb(150, 150, 150);
pub const SHELL_COLOR: Color32 = Color32::from_rgb(120, 120, 130);
pub const PLANE_FIT_COLOR: Color32 = Color32::from_rgb(230, 60, 60);
pub const REJECTED_COLOR: Color32 = Color32::from_rgb(130, 130, 130);
pub const CAMERA_ESTIMATE_COLOR: Color32 = Color32::from_rgb(110, 170, 255);
pub const FUSED_COLOR: Color32 = Color32::from_rgb(40, 90, 255);
pub const TRUTH_COLOR: Color32 = Color32::from_rgb(230, 60, 230);
pub const PATCH_COLOR: Color32 = Color32::from_rgb(60, 190, 170);
/// A keep-off guard (its core's silhouette and its outermost shell), and its fused surface.
pub const GUARD_COLOR: Color32 = Color32::from_rgb(80, 200, 120);

/// Circle fits cycle through these (paper Fig. 7: green and yellow circle normals).
const CIRCLE_FIT_COLORS: [Color32; 4] = [
    Color32::from_rgb(70, 210, 70),
    Color32::from_rgb(240, 220, 50),
    Color32::from_rgb(60, 200, 220),
    Color32::from_rgb(240, 150, 60),
];

/// Colour of a shell fit by its kind and position among the circles.
pub fn fit_color(fit: &ShellFit, circle_index: usize) -> Color32 {
    if fit.rejected {
        REJECTED_COLOR
    } else if fit.kind == ShellFitKind::Plane {
        PLANE_FIT_COLOR
    } else {
        CIRCLE_FIT_COLORS[circle_index % CIRCLE_FIT_COLORS.len()]
    }
}

/// Colour of the HIP sphere for the frame's haptic state: yellow without constraint data or
/// while the HIP is too far, orange while the constraints are in force, red while one binds,
/// grey without a tracking surface.
pub fn hip_color(frame: &ViewFrame) -> Color32 {
    let s = &frame.samples;
    match s.haptic_status {
        None | Some(HapticStatus::Far) => HIP_COLOR,
        Some(HapticStatus::NoSurface) => HIP_NO_SURFACE_COLOR,
        Some(HapticStatus::Active) if s.constraints.iter().any(|c| c.binding == Some(true)) => {
            HIP_BINDING_COLOR
        }
        Some(HapticStatus::Active) => HIP_ACTIVE_COLOR,
    }
}

/// Which elements are drawn (each one is a toggle in the layer panel).
#[derive(Clone, Debug, PartialEq)]
pub struct Layers {
    pub roles: BTreeMap<PointRole, bool>,
    /// Cameras hidden by the user (all others are drawn).
    pub hidden_cameras: Vec<u32>,
    pub hip: bool,
    /// The HIP's projection on the fused surface plane (what eq. 7 measures).
    pub hip_projection: bool,
    pub shells: bool,
    pub shell_fits: bool,
    pub camera_estimates: bool,
    pub patch: bool,
    pub fused: bool,
    pub truth: bool,
    /// The keep-off guards with their shells and fused surfaces.
    pub guards: bool,
}

impl Default for Layers {
    fn default() -> Self {
        Self {
            roles: PointRole::ALL.iter().map(|&r| (r, true)).collect(),
            hidden_cameras: Vec::new(),
            hip: true,
            hip_projection: true,
            shells: true,
            shell_fits: true,
            camera_estimates: true,
            patch: true,
            fused: true,
            truth: true,
            guards: true,
        }
    }
}

impl Layers {
    pub fn role_visible(&self, role: PointRole) -> bool {
        self.roles.get(&role).copied().unwrap_or(true)
    }

    pub fn camera_visible(&self, camera_id: u32) -> bool {
        !self.hidden_cameras.contains(&camera_id)
    }
}

/// Counts of what one call of [`paint_frame`] drew.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct DrawStats {
    pub points: usize,
    pub shell_spheres: usize,
    pub fits: usize,
    pub rejected_fits: usize,
    /// Camera estimates drawn.
    pub estimates: usize,
    /// Camera estimates without a surface (nothing to draw).
    pub rejected_estimates: usize,
    pub patch_triangles: usize,
    pub fused: bool,
    pub truth: bool,
    /// The HIP's projection on the fused surface plane was drawn.
    pub hip_projection: bool,
    /// Colour the HIP sphere was drawn in (None when hidden or off screen).
    pub hip_color: Option<Color32>,
    /// Keep-off guards drawn (their cores on screen).
    pub guards: usize,
}

/// Display sizes.
#[derive(Clone, Copy, Debug)]
pub struct DrawStyle {
    pub point_size_px: f32,
    pub normal_length_m: f64,
    /// A layer with more points is drawn with every k-th point (k as small as possible).
    pub max_points_per_layer: usize,
}

/// The stride that draws at most `max` of `len` points.
pub fn display_stride(len: usize, max: usize) -> usize {
    len.div_ceil(max.max(1)).max(1)
}

fn v3(p: &Point3<f64>) -> Vec3 {
    Vec3::new(p.x as f32, p.y as f32, p.z as f32)
}

fn d3(v: &Vector3<f64>) -> Vec3 {
    Vec3::new(v.x as f32, v.y as f32, v.z as f32)
}

/// Two unit vectors spanning the plane orthogonal to `n`.
fn plane_basis(n: Vec3) -> (Vec3, Vec3) {
    let u = n.any_orthonormal_vector();
    (u, n.cross(u))
}

/// Screen points of a 3D circle (open: the first point is not repeated), or `None` if any
/// point is behind the eye.
fn circle_points(proj: &Projector, centre: Vec3, normal: Vec3, radius_m: f32) -> Option<Vec<Pos2>> {
    const SEGMENTS: usize = 64;
    let (u, v) = plane_basis(normal);
    (0..SEGMENTS)
        .map(|k| {
            let a = k as f32 / SEGMENTS as f32 * std::f32::consts::TAU;
            proj.project(centre + radius_m * (a.cos() * u + a.sin() * v))
                .map(|(p, _)| p)
        })
        .collect()
}

/// An arrow from `origin` along `dir` (world units), with a dot at its origin.
fn paint_vector(
    painter: &Painter,
    proj: &Projector,
    origin: Vec3,
    dir: Vec3,
    stroke: Stroke,
) -> bool {
    let (Some((a, _)), Some((b, _))) = (proj.project(origin), proj.project(origin + dir)) else {
        return false;
    };
    painter.circle_filled(a, stroke.width + 1.5, stroke.color);
    painter.arrow(a, b - a, stroke);
    true
}

fn paint_surface_point(
    painter: &Painter,
    proj: &Projector,
    s: &SurfacePoint,
    style: &DrawStyle,
    stroke: Stroke,
) -> bool {
    let dir = d3(&s.normal.into_inner()) * style.normal_length_m as f32;
    paint_vector(painter, proj, v3(&s.centroid_m), dir, stroke)
}

fn paint_points(
    painter: &Painter,
    proj: &Projector,
    frame: &ViewFrame,
    layers: &Layers,
    style: &DrawStyle,
) -> usize {
    let mut mesh = Mesh::default();
    let half = Vec2::splat(0.5 * style.point_size_px);
    let mut count = 0;
    for role in PointRole::ALL {
        if !layers.role_visible(role) {
            continue;
        }
        let color = role_color(role);
        for cam in frame
            .cameras
            .iter()
            .filter(|c| layers.camera_visible(c.camera_id))
        {
            let pts = cam.layer(role);
            let stride = display_stride(pts.len(), style.max_points_per_layer);
            for p in pts.iter().step_by(stride) {
                if let Some((pos, _)) = proj.project(*p)
                    && proj.rect().contains(pos)
                {
                    mesh.add_colored_rect(egui::Rect::from_min_max(pos - half, pos + half), color);
                    count += 1;
                }
            }
        }
    }
    painter.add(Shape::mesh(mesh));
    count
}

fn paint_patch(painter: &Painter, proj: &Projector, patch: &SurfacePatch, eye_dir: Vec3) -> usize {
    let projected: Vec<Option<(Pos2, f32)>> =
        patch.vertices_m.iter().map(|p| proj.project(*p)).collect();
    let mut tris: Vec<(f32, [Pos2; 3], f32)> = Vec::with_capacity(patch.triangles.len());
    for t in &patch.triangles {
        let [Some(a), Some(b), Some(c)] = t.map(|i| projected[i as usize]) else {
            continue;
        };
        let [pa, pb, pc] = t.map(|i| patch.vertices_m[i as usize]);
        let facing = (pb - pa)
            .cross(pc - pa)
            .normalize_or_zero()
            .dot(eye_dir)
            .abs();
        tris.push(((a.1 + b.1 + c.1) / 3.0, [a.0, b.0, c.0], facing));
    }
    // Far triangles first.
    tris.sort_by(|x, y| y.0.total_cmp(&x.0));
    let mut mesh = Mesh::default();
    for (_, pts, facing) in &tris {
        let shade = 0.35 + 0.65 * facing;
        let c = PATCH_COLOR;
        let color = Color32::from_rgba_unmultiplied(
            (c.r() as f32 * shade) as u8,
            (c.g() as f32 * shade) as u8,
            (c.b() as f32 * shade) as u8,
            110,
        );
        let base = mesh.vertices.len() as u32;
        for p in pts {
            mesh.colored_vertex(*p, color);
        }
        mesh.add_triangle(base, base + 1, base + 2);
    }
    painter.add(Shape::mesh(mesh));
    tris.len()
}

fn paint_fit(
    painter: &Painter,
    proj: &Projector,
    fit: &ShellFit,
    color: Color32,
    style: &DrawStyle,
) -> bool {
    let centre = v3(&fit.center_m);
    let normal = d3(&fit.normal.into_inner());
    let width = if fit.rejected { 1.0 } else { 2.0 };
    let stroke = Stroke::new(width, color);
    let outline_radius = match fit.kind {
        ShellFitKind::Circle => fit.circle_radius_m.unwrap_or(fit.outer_radius_m),
        ShellFitKind::Plane => fit.outer_radius_m,
    } as f32;
    let Some(mut outline) = circle_points(proj, centre, normal, outline_radius) else {
        return false;
    };
    if fit.rejected {
        outline.push(outline[0]);
        painter.add(Shape::dashed_line(&outline, stroke, 4.0, 4.0));
    } else if fit.kind == ShellFitKind::Plane {
        painter.add(Shape::convex_polygon(
            outline,
            color.gamma_multiply(0.25),
            stroke,
        ));
    } else {
        painter.add(Shape::closed_line(outline, stroke));
    }
    paint_vector(
        painter,
        proj,
        centre,
        normal * style.normal_length_m as f32,
        stroke,
    );
    if fit.rejected {
        paint_cross(painter, proj, centre);
    }
    true
}

/// A red cross marking something rejected at world point `at`.
fn paint_cross(painter: &Painter, proj: &Projector, at: Vec3) {
    if let Some((c, _)) = proj.project(at) {
        let cross = Stroke::new(2.0, Color32::from_rgb(220, 40, 40));
        let d = 5.0;
        painter.line_segment([c + Vec2::new(-d, -d), c + Vec2::new(d, d)], cross);
        painter.line_segment([c + Vec2::new(-d, d), c + Vec2::new(d, -d)], cross);
    }
}

/// The HIP centre's foot on the fused surface's tangent plane: a dashed line from the HIP
/// centre, a disc of the HIP's radius in the plane and `d_proj` written beside it, in the
/// colour of the constraint state.
fn paint_hip_projection(painter: &Painter, proj: &Projector, frame: &ViewFrame) -> bool {
    let (Some(foot), Some(fused)) = (frame.hip_projection(), frame.fused.as_ref()) else {
        return false;
    };
    let color = hip_color(frame);
    let (Some((a, _)), Some((b, _))) = (proj.project(v3(&frame.hip_m)), proj.project(v3(&foot)))
    else {
        return false;
    };
    let stroke = Stroke::new(1.5, color);
    painter.add(Shape::dashed_line(&[a, b], stroke, 5.0, 3.0));
    let normal = d3(&fused.normal.into_inner());
    if let Some(disc) = circle_points(proj, v3(&foot), normal, frame.hip_radius_m as f32) {
        painter.add(Shape::convex_polygon(
            disc,
            color.gamma_multiply(0.2),
            stroke,
        ));
    }
    painter.circle_filled(b, 3.0, color);
    if let Some(d) = frame.samples.d_proj_m {
        painter.text(
            b + Vec2::new(8.0, 8.0),
            egui::Align2::LEFT_TOP,
            format!("d_proj {:.1} mm", d * 1e3),
            egui::FontId::proportional(11.0),
            color,
        );
    }
    true
}

/// A small world-axis triad in the lower left corner (x red, y green, z blue).
fn paint_axes(painter: &Painter, proj: &Projector, target: Vec3, eye_distance_m: f32) {
    let Some((o, _)) = proj.project(target) else {
        return;
    };
    let origin = proj.rect().left_bottom() + Vec2::new(30.0, -30.0);
    for (axis, color, label) in [
        (Vec3::X, Color32::from_rgb(220, 70, 70), "x"),
        (Vec3::Y, Color32::from_rgb(70, 200, 70), "y"),
        (Vec3::Z, Color32::from_rgb(80, 120, 255), "z"),
    ] {
        let Some((tip, _)) = proj.project(target + axis * 0.1 * eye_distance_m) else {
            continue;
        };
        let dir = (tip - o).normalized() * 22.0;
        painter.arrow(origin, dir, Stroke::new(1.5, color));
        painter.text(
            origin + dir * 1.3,
            egui::Align2::CENTER_CENTER,
            label,
            egui::FontId::monospace(10.0),
            color,
        );
    }
}

/// Paint `frame` into the projector's rectangle; `patches` holds one surface patch per camera id.
pub fn paint_frame(
    painter: &Painter,
    orbit: &OrbitCamera,
    proj: &Projector,
    frame: &ViewFrame,
    patches: &[(u32, SurfacePatch)],
    layers: &Layers,
    style: &DrawStyle,
) -> DrawStats {
    let mut stats = DrawStats {
        points: paint_points(painter, proj, frame, layers, style),
        ..DrawStats::default()
    };

    if layers.patch {
        for (_, patch) in patches.iter().filter(|(c, _)| layers.camera_visible(*c)) {
            stats.patch_triangles += paint_patch(painter, proj, patch, orbit.eye_dir());
        }
    }

    let hip = v3(&frame.hip_m);
    if let Some((hip_px, depth)) = proj.project(hip) {
        if layers.shells {
            for (i, r) in frame.shell_radii_m.iter().enumerate() {
                let outer = i + 1 == frame.shell_radii_m.len();
                let stroke = Stroke::new(
                    if outer { 1.5 } else { 1.0 },
                    SHELL_COLOR.gamma_multiply(if outer { 1.0 } else { 0.7 }),
                );
                let radius_px = proj.radius_px(*r as f32, depth);
                painter.circle_stroke(hip_px, radius_px, stroke);
                stats.shell_spheres += 1;
                if i == 0 || outer {
                    let name = if outer { "r_out" } else { "r_in" };
                    painter.text(
                        hip_px - Vec2::new(0.0, radius_px + 2.0),
                        egui::Align2::CENTER_BOTTOM,
                        format!("{name} {:.0} mm", r * 1e3),
                        egui::FontId::proportional(10.0),
                        SHELL_COLOR,
                    );
                }
            }
        }
        if layers.hip {
            let r = proj.radius_px(frame.hip_radius_m as f32, depth);
            let color = hip_color(frame);
            painter.circle(
                hip_px,
                r,
                color.gamma_multiply(0.45),
                Stroke::new(1.5, color),
            );
            stats.hip_color = Some(color);
        }
    }
    if layers.hip_projection {
        stats.hip_projection = paint_hip_projection(painter, proj, frame);
    }

    for cam in frame
        .cameras
        .iter()
        .filter(|c| layers.camera_visible(c.camera_id))
    {
        let Some(est) = &cam.estimate else { continue };
        if layers.shell_fits {
            let mut circle_index = 0;
            for fit in &est.shells {
                let color = fit_color(fit, circle_index);
                if fit.kind == ShellFitKind::Circle {
                    circle_index += 1;
                }
                if paint_fit(painter, proj, fit, color, style) {
                    stats.fits += 1;
                    stats.rejected_fits += usize::from(fit.rejected);
                }
            }
        }
        match &est.surface {
            Some(s)
                if layers.camera_estimates && s.centroid_m.coords.iter().all(|v| v.is_finite()) =>
            {
                let stroke = Stroke::new(2.0, CAMERA_ESTIMATE_COLOR);
                if paint_surface_point(painter, proj, s, style, stroke) {
                    stats.estimates += 1;
                }
            }
            Some(_) => {}
            None => stats.rejected_estimates += 1,
        }
    }

    if layers.truth
        && let Some(t) = &frame.truth
    {
        stats.truth = paint_surface_point(painter, proj, t, style, Stroke::new(2.5, TRUTH_COLOR));
    }
    if layers.fused
        && let Some(f) = &frame.fused
    {
        stats.fused = paint_surface_point(painter, proj, f, style, Stroke::new(3.0, FUSED_COLOR));
    }
    if layers.guards {
        for g in &frame.guards {
            stats.guards += usize::from(paint_guard(painter, proj, g, layers, style));
        }
    }
    paint_axes(painter, proj, orbit.target_m, orbit.distance_m);
    stats
}

/// A keep-off guard: its core's silhouette (a circle of its radius at each end of the
/// segment, joined), its outermost shell around the latest shells' origin, its fused
/// surface and its name with `d_proj`; false when the core is off screen.
fn paint_guard(
    painter: &Painter,
    proj: &Projector,
    g: &GuardView,
    layers: &Layers,
    style: &DrawStyle,
) -> bool {
    let (Some((a, da)), Some((b, db))) = (proj.project(v3(&g.a_m)), proj.project(v3(&g.b_m)))
    else {
        return false;
    };
    let near = g.d_proj_m.is_some_and(|d| d < 0.02);
    let color = if near { HIP_BINDING_COLOR } else { GUARD_COLOR };
    let stroke = Stroke::new(1.5, color);
    let (ra, rb) = (
        proj.radius_px(g.radius_m as f32, da),
        proj.radius_px(g.radius_m as f32, db),
    );
    painter.circle(a, ra, color.gamma_multiply(0.25), stroke);
    painter.circle(b, rb, color.gamma_multiply(0.25), stroke);
    painter.line_segment(
        [a, b],
        Stroke::new(ra.min(rb).max(1.0) * 2.0, color.gamma_multiply(0.25)),
    );
    if layers.shells
        && let (Some(origin), Some(r)) = (g.origin_m, g.shell_radii_m.last())
        && let Some((o, depth)) = proj.project(v3(&origin))
    {
        painter.circle_stroke(
            o,
            proj.radius_px(*r as f32, depth),
            Stroke::new(1.0, SHELL_COLOR),
        );
    }
    if let Some(f) = &g.fused {
        paint_surface_point(painter, proj, f, style, Stroke::new(2.0, GUARD_COLOR));
    }
    let label = match g.d_proj_m {
        Some(d) => format!("{} {:.0} mm", g.name, d * 1e3),
        None => g.name.clone(),
    };
    painter.text(
        a.lerp(b, 0.5) - Vec2::new(0.0, ra.max(rb) + 2.0),
        egui::Align2::CENTER_BOTTOM,
        label,
        egui::FontId::proportional(10.0),
        color,
    );
    true
}

#[cfg(test)]
mod tests {
    use super::display_stride;

    #[test]
    fn stride_caps_the_drawn_points() {
        assert_eq!(display_stride(0, 100), 1);
        assert_eq!(display_stride(100, 100), 1);
        assert_eq!(display_stride(101, 100), 2);
        assert_eq!(display_stride(400_000, 50_000), 8);
        assert_eq!(display_stride(10, 0), 10);
        for len in [1usize, 7, 99, 100, 101, 12_345] {
            assert!(len.div_ceil(display_stride(len, 100)) <= 100);
        }
    }
}
