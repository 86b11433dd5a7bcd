//! Rigid-body dynamics of the exoskeleton: a compact Featherstone implementation in f64.
//!
//! Spatial vectors are `[angular; linear]` in link coordinates (Featherstone, "Rigid Body
//! Dynamics Algorithms", 2008). `X_i` is the motion transform from the parent's coordinates to
//! link `i`'s; forces move back with `X_i^T`. Gravity enters as a fictitious upward
//! acceleration of the base. The algorithms:
//! - RNEA (Featherstone Table 5.1): inverse dynamics `tau = M(q) qdd + h(q, qd)`; with
//!   `qdd = 0` it gives the bias forces `h` = Coriolis, centrifugal and gravity terms.
//! - CRBA (Table 6.2): the joint-space mass matrix `M(q)` from composite inertias.
//! - Forward dynamics `qdd = M^-1 (tau - h)` by Cholesky.
//!
//! Fixed joints carry no DoF: their link simply rides on the parent. Written by hand rather
//! than pulled from a crate because the maintained Rust options (`k` for kinematics only,
//! `rapier`/`nphysics` for simulation) expose neither M nor h for a URDF chain; the tests
//! check it against finite differences of the kinetic energy and against energy
//! conservation in a passive simulation.

use super::{GRAVITY_MPS2, JointKind, JointMatrix, JointVector, PerLink, RobotModel, skew};
use nalgebra::{Matrix3, Matrix6, Vector3, Vector6};

/// Motion transform from a parent's coordinates to a child's: `[E 0; -E r^ E]` with `E` the
/// child-from-parent rotation and `r` the child origin in parent coordinates.
fn motion_transform(e: &Matrix3<f64>, r: &Vector3<f64>) -> Matrix6<f64> {
    let mut x = Matrix6::zeros();
    x.fixed_view_mut::<3, 3>(0, 0).copy_from(e);
    x.fixed_view_mut::<3, 3>(3, 3).copy_from(e);
    x.fixed_view_mut::<3, 3>(3, 0).copy_from(&(-e * skew(r)));
    x
}

/// Spatial cross product for motion vectors, `v x m`.
fn cross_motion(v: &Vector6<f64>, m: &Vector6<f64>) -> Vector6<f64> {
    let (w, u) = (v.fixed_rows::<3>(0), v.fixed_rows::<3>(3));
    let (mw, mu) = (m.fixed_rows::<3>(0), m.fixed_rows::<3>(3));
    let ang = w.cross(&mw);
    let lin = w.cross(&mu) + u.cross(&mw);
    Vector6::new(ang.x, ang.y, ang.z, lin.x, lin.y, lin.z)
}

/// Spatial cross product for force vectors, `v x* f`.
fn cross_force(v: &Vector6<f64>, f: &Vector6<f64>) -> Vector6<f64> {
    let (w, u) = (v.fixed_rows::<3>(0), v.fixed_rows::<3>(3));
    let (fn_, ff) = (f.fixed_rows::<3>(0), f.fixed_rows::<3>(3));
    let ang = w.cross(&fn_) + u.cross(&ff);
    let lin = w.cross(&ff);
    Vector6::new(ang.x, ang.y, ang.z, lin.x, lin.y, lin.z)
}

/// Spatial inertia about the link origin from mass, centre of mass and rotational inertia
/// about the centre of mass: `[Ic + m c^ c^T, m c^; m c^T, m 1]`.
fn spatial_inertia(mass: f64, com: &Vector3<f64>, inertia_com: &Matrix3<f64>) -> Matrix6<f64> {
    let c = skew(com);
    let mut i = Matrix6::zeros();
    i.fixed_view_mut::<3, 3>(0, 0)
        .copy_from(&(inertia_com + c * c.transpose() * mass));
    i.fixed_view_mut::<3, 3>(0, 3).copy_from(&(c * mass));
    i.fixed_view_mut::<3, 3>(3, 0)
        .copy_from(&(c.transpose() * mass));
    i.fixed_view_mut::<3, 3>(3, 3)
        .copy_from(&(Matrix3::identity() * mass));
    i
}

/// Per-link quantities shared by RNEA and CRBA for one `q`.
struct LinkStates {
    /// Motion transform parent -> link (identity-sized zero for the root, unused).
    x: PerLink<Matrix6<f64>>,
    /// Motion subspace (unit twist of the joint) or zero for fixed joints.
    s: PerLink<Vector6<f64>>,
    /// DoF index of the link's joint.
    dof: PerLink<Option<usize>>,
}

/// Why a dynamics query failed.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum DynamicsError {
    #[error("mass matrix is not positive definite")]
    SingularMassMatrix,
}

impl RobotModel {
    fn link_states(&self, q: &JointVector) -> LinkStates {
        let (mut x, mut s, mut dof) = (PerLink::new(), PerLink::new(), PerLink::new());
        for (i, link) in self.links.iter().enumerate() {
            let parent_from_link = self.parent_from_link(i, q);
            let e = parent_from_link
                .rotation
                .to_rotation_matrix()
                .matrix()
                .transpose();
            x.push(motion_transform(&e, &parent_from_link.translation.vector));
            match &link.joint {
                JointKind::Revolute { dof: d, axis } => {
                    s.push(Vector6::new(axis.x, axis.y, axis.z, 0.0, 0.0, 0.0));
                    dof.push(Some(*d));
                }
                _ => {
                    s.push(Vector6::zeros());
                    dof.push(None);
                }
            }
        }
        LinkStates { x, s, dof }
    }

    fn link_inertia(&self, i: usize) -> Matrix6<f64> {
        let l = &self.links[i];
        spatial_inertia(l.mass_kg, &l.com_m.coords, &l.inertia_com_kgm2)
    }

    /// Gravity as an upward base acceleration, in base coordinates (`gravity_scale` 0 or 1).
    fn base_acceleration(&self, gravity_scale: f64) -> Vector6<f64> {
        let up = self.world_from_base.rotation.inverse()
            * Vector3::new(0.0, 0.0, GRAVITY_MPS2 * gravity_scale);
        Vector6::new(0.0, 0.0, 0.0, up.x, up.y, up.z)
    }

    fn rnea(
        &self,
        q: &JointVector,
        qd: &JointVector,
        qdd: &JointVector,
        gravity_scale: f64,
    ) -> JointVector {
        let st = self.link_states(q);
        let n = self.links.len();
        let zeros = || (0..n).map(|_| Vector6::zeros()).collect::<PerLink<_>>();
        let (mut v, mut a, mut f) = (zeros(), zeros(), zeros());
        a[0] = self.base_acceleration(gravity_scale);
        for i in 1..n {
            let Some(p) = self.links[i].parent else {
                continue;
            };
            let (qdi, qddi) = st.dof[i].map_or((0.0, 0.0), |d| (qd[d], qdd[d]));
            let vj = st.s[i] * qdi;
            v[i] = st.x[i] * v[p] + vj;
            a[i] = st.x[i] * a[p] + st.s[i] * qddi + cross_motion(&v[i], &vj);
            let inertia = self.link_inertia(i);
            f[i] = inertia * a[i] + cross_force(&v[i], &(inertia * v[i]));
        }
        let mut tau = JointVector::zeros();
        for i in (1..n).rev() {
            if let Some(d) = st.dof[i] {
                tau[d] = st.s[i].dot(&f[i]);
            }
            if let Some(p) = self.links[i].parent {
                let back = st.x[i].transpose() * f[i];
                f[p] += back;
            }
        }
        tau
    }

    /// Inverse dynamics (RNEA): the torques that produce `qdd` at state `(q, qd)`, Nm.
    pub fn inverse_dynamics(
        &self,
        q: &JointVector,
        qd: &JointVector,
        qdd: &JointVector,
    ) -> JointVector {
        self.rnea(q, qd, qdd, 1.0)
    }

    /// Bias forces `h(q, qd)`: Coriolis, centrifugal and gravity torques, Nm.
    pub fn bias_forces(&self, q: &JointVector, qd: &JointVector) -> JointVector {
        self.rnea(q, qd, &JointVector::zeros(), 1.0)
    }

    /// Gravity torques `g(q)`, Nm.
    pub fn gravity_torques(&self, q: &JointVector) -> JointVector {
        self.rnea(q, &JointVector::zeros(), &JointVector::zeros(), 1.0)
    }

    /// Joint-space mass matrix `M(q)` (CRBA), kg m^2.
    pub fn mass_matrix(&self, q: &JointVector) -> JointMatrix {
        let st = self.link_states(q);
        let n = self.links.len();
        let mut ic: PerLink<Matrix6<f64>> = (0..n).map(|i| self.link_inertia(i)).collect();
        for i in (1..n).rev() {
            if let Some(p) = self.links[i].parent {
                let add = st.x[i].transpose() * ic[i] * st.x[i];
                ic[p] += add;
            }
        }
        let mut m = JointMatrix::zeros();
        for (i, ic_i) in ic.iter().enumerate().skip(1) {
            let Some(di) = st.dof[i] else {
                continue;
            };
            let mut force = ic_i * st.s[i];
            m[(di, di)] = st.s[i].dot(&force);
            let mut j = i;
            while let Some(p) = self.links[j].parent {
                force = st.x[j].transpose() * force;
                j = p;
                if let Some(dj) = st.dof[j] {
                    m[(di, dj)] = st.s[j].dot(&force);
                    m[(dj, di)] = m[(di, dj)];
                }
            }
        }
        m
    }

    /// Forward dynamics: `qdd = M^-1 (tau - h)`, rad/s^2.
    pub fn forward_dynamics(
        &self,
        q: &JointVector,
        qd: &JointVector,
        tau: &JointVector,
    ) -> Result<JointVector, DynamicsError> {
        let m = self.mass_matrix(q);
        let rhs = tau - self.bias_forces(q, qd);
        m.cholesky()
            .map(|c| c.solve(&rhs))
            .ok_or(DynamicsError::SingularMassMatrix)
    }

    /// Kinetic energy `1/2 qd^T M qd`, J.
    pub fn kinetic_energy(&self, q: &JointVector, qd: &JointVector) -> f64 {
        0.5 * qd.dot(&(self.mass_matrix(q) * qd))
    }

    /// Gravitational potential energy `sum m g z_com` (world z up), J.
    pub fn potential_energy(&self, q: &JointVector) -> f64 {
        let poses = self.forward_kinematics(q);
        self.links
            .iter()
            .zip(&poses)
            .map(|(l, pose)| l.mass_kg * GRAVITY_MPS2 * (pose * l.com_m).z)
            .sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Isometry3, Translation3, UnitQuaternion};

    fn model() -> RobotModel {
        RobotModel::anyexo().expect("embedded URDF parses")
    }

    fn state() -> (JointVector, JointVector) {
        (
            JointVector::from_column_slice(&[0.1, -0.2, 0.4, 0.3, 0.9, 1.2]),
            JointVector::from_column_slice(&[0.5, -0.3, 0.8, -1.1, 0.6, 1.4]),
        )
    }

    #[test]
    fn mass_matrix_is_symmetric_positive_definite_and_matches_rnea() {
        let m = model();
        let (q, qd) = state();
        let mm = m.mass_matrix(&q);
        assert!((mm - mm.transpose()).norm() < 1e-12);
        assert!(mm.symmetric_eigenvalues().min() > 0.0);
        // columns of M from RNEA without velocity and gravity
        for j in 0..6 {
            let e = JointVector::from_fn(|i, _| if i == j { 1.0 } else { 0.0 });
            let col = m.rnea(&q, &JointVector::zeros(), &e, 0.0);
            assert!((col - mm.column(j)).norm() < 1e-12, "column {j}");
        }
        let tau = m.inverse_dynamics(&q, &qd, &e3());
        assert!((tau - (mm * e3() + m.bias_forces(&q, &qd))).norm() < 1e-12);
    }

    fn e3() -> JointVector {
        JointVector::from_column_slice(&[0.3, -1.0, 2.0, 0.5, -0.7, 1.1])
    }

    #[test]
    fn gravity_is_gradient_of_potential_energy() {
        let m = model();
        let (q, _) = state();
        let g = m.gravity_torques(&q);
        let h = 1e-6;
        for j in 0..6 {
            let mut qp = q;
            let mut qm = q;
            qp[j] += h;
            qm[j] -= h;
            let fd = (m.potential_energy(&qp) - m.potential_energy(&qm)) / (2.0 * h);
            assert!((g[j] - fd).abs() < 1e-6, "joint {j}: {} vs {fd}", g[j]);
        }
    }

    #[test]
    fn coriolis_matches_lagrangian_finite_differences() {
        // h - g = Mdot qd - d/dq (1/2 qd^T M qd)
        let m = model();
        let (q, qd) = state();
        let c = m.bias_forces(&q, &qd) - m.gravity_torques(&q);
        let h = 1e-6;
        let mdot = (m.mass_matrix(&(q + qd * h)) - m.mass_matrix(&(q - qd * h))) / (2.0 * h);
        let mut dt_dq = JointVector::zeros();
        for j in 0..6 {
            let mut qp = q;
            let mut qm = q;
            qp[j] += h;
            qm[j] -= h;
            dt_dq[j] = (m.kinetic_energy(&qp, &qd) - m.kinetic_energy(&qm, &qd)) / (2.0 * h);
        }
        let expected = mdot * qd - dt_dq;
        assert!((c - expected).norm() < 1e-6, "{c} vs {expected}");
    }

    #[test]
    fn hip_acceleration_agrees_with_rnea_point_kinematics() {
        // a point mass at the HIP adds J^T m J to the mass matrix (finite-difference check of
        // the HIP Jacobian against CRBA with a modified link)
        let m = model();
        let (q, _) = state();
        let mut heavy = m.clone();
        let hip = heavy.hip_link();
        heavy.links[hip].mass_kg = 2.0;
        let jac = m.hip_kinematics(&q, &JointVector::zeros()).jacobian;
        let diff = heavy.mass_matrix(&q) - m.mass_matrix(&q);
        assert!((diff - jac.transpose() * jac * 2.0).norm() < 1e-12);
    }

    #[test]
    fn passive_simulation_conserves_energy() {
        // RK4 with no torque: kinetic + potential energy stays constant.
        let m = model().with_base(Isometry3::from_parts(
            Translation3::new(0.0, 0.0, 1.2),
            UnitQuaternion::from_euler_angles(0.1, -0.05, 0.3),
        ));
        let (mut q, mut qd) = state();
        let energy =
            |q: &JointVector, qd: &JointVector| m.kinetic_energy(q, qd) + m.potential_energy(q);
        let e0 = energy(&q, &qd);
        let dt = 1e-4;
        let zero = JointVector::zeros();
        let f = |q: &JointVector, qd: &JointVector| m.forward_dynamics(q, qd, &zero).unwrap();
        for _ in 0..10_000 {
            let k1q = qd;
            let k1v = f(&q, &qd);
            let k2q = qd + k1v * (dt / 2.0);
            let k2v = f(&(q + k1q * (dt / 2.0)), &k2q);
            let k3q = qd + k2v * (dt / 2.0);
            let k3v = f(&(q + k2q * (dt / 2.0)), &k3q);
            let k4q = qd + k3v * dt;
            let k4v = f(&(q + k3q * dt), &k4q);
            q += (k1q + k2q * 2.0 + k3q * 2.0 + k4q) * (dt / 6.0);
            qd += (k1v + k2v * 2.0 + k3v * 2.0 + k4v) * (dt / 6.0);
        }
        let e1 = energy(&q, &qd);
        assert!((e1 - e0).abs() < 1e-6 * e0.abs().max(1.0), "{e0} -> {e1}");
        // and the motion was not trivial
        assert!((q - state().0).norm() > 0.1);
    }
}
