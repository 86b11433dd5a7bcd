//! Plane and circle fits on point moments, in f64 (paper Alg. 2: `plane3d` and `circle3d`).
//!
//! Every fit here consumes [`Moments`]: the sums over a point set of all monomials
//! `dx^i dy^j dz^k` with `i + j + k <= 4` of the offsets `d = p - origin` from a chosen origin
//! (the HIP for the shells). Moments are additive, so the GPU can reduce them per shell and the
//! CPU fits never see the points (paper IV-E; design card: "per-shell covariance accumulation on
//! the GPU, CPU-side circle fits").
//!
//! - [`plane3d`]: centroid and normal of the point set. The normal is the eigenvector of the
//!   smallest eigenvalue of the 3x3 covariance, from nalgebra's symmetric QR eigen solver
//!   (never the closed-form Cardano one). Fewer than 3 points, or a second eigenvalue that is a
//!   negligible fraction of the largest (collinear or coincident points), is reported as
//!   [`FitError`], never returned as a normal.
//! - [`circle3d`]: the plane first; then the Rodrigues rotation taking the normal onto `z`
//!   (nalgebra's `rotation_between`) gives the in-plane axes `e1, e2`, the planar moments
//!   `sum u^p v^q` (p + q <= 4) follow from the 3D moments by polynomial contraction, are
//!   shifted to the planar centroid, and one of three centre estimators runs:
//!   [`CircleMethod::Kasa`] (algebraic least squares, biased towards small radii on short
//!   arcs), [`CircleMethod::Taubin`] (gradient-weighted algebraic fit, solved by Newton on its
//!   characteristic cubic as in Chernov's reference code; nearly unbiased on arcs), and
//!   [`CircleMethod::SphereCut`] (closed form: the circle where the fitted plane cuts the sphere
//!   around the origin through the points, i.e. the origin projected onto the plane; needs only
//!   second moments and can never blow up). A nearly straight arc sends an algebraic radius to
//!   infinity: radii above the caller's limit, or non-finite ones, fall back to the sphere cut
//!   and say so (`fell_back`).

use nalgebra::{Matrix3, Point3, Rotation3, SymmetricEigen, Unit, Vector3};
use serde::{Deserialize, Serialize};

/// Highest monomial degree kept in [`Moments`] (fourth moments: Taubin needs `sum z^2`,
/// `z = u^2 + v^2`).
pub const MAX_DEGREE: usize = 4;
/// Number of monomials of degree <= 4 in three variables.
pub const MOMENT_COUNT: usize = 35;

/// Exponents `[i, j, k]` of the monomial `dx^i dy^j dz^k` stored at each index: by degree,
/// then lexicographically with `x` first. Shared with the GPU shader (uploaded as a table).
pub const EXPONENTS: [[u8; 3]; MOMENT_COUNT] = exponents();

/// For each monomial of degree >= 1: the index of the monomial it extends and the axis it is
/// multiplied by (`m[n] = m[PARENT[n]] * s[AXIS[n]]`). Entry 0 (the constant) is unused.
/// The CPU reference and the shader evaluate monomials in exactly this order.
pub const PARENT: [u32; MOMENT_COUNT] = parents().0;
pub const AXIS: [u32; MOMENT_COUNT] = parents().1;

const fn exponents() -> [[u8; 3]; MOMENT_COUNT] {
    let mut out = [[0u8; 3]; MOMENT_COUNT];
    let mut n = 0;
    let mut degree = 0u8;
    while degree as usize <= MAX_DEGREE {
        let mut i = degree as i32;
        while i >= 0 {
            let mut j = degree as i32 - i;
            while j >= 0 {
                let k = degree as i32 - i - j;
                out[n] = [i as u8, j as u8, k as u8];
                n += 1;
                j -= 1;
            }
            i -= 1;
        }
        degree += 1;
    }
    out
}

/// Index of the monomial with exponents `e` (degree <= 4).
pub const fn monomial_index(e: [u8; 3]) -> usize {
    let mut n = 0;
    while n < MOMENT_COUNT {
        let x = EXPONENTS[n];
        if x[0] == e[0] && x[1] == e[1] && x[2] == e[2] {
            return n;
        }
        n += 1;
    }
    panic!("monomial degree above MAX_DEGREE")
}

const fn parents() -> ([u32; MOMENT_COUNT], [u32; MOMENT_COUNT]) {
    let mut parent = [0u32; MOMENT_COUNT];
    let mut axis = [0u32; MOMENT_COUNT];
    let mut n = 1;
    while n < MOMENT_COUNT {
        let e = EXPONENTS[n];
        let a = if e[0] > 0 {
            0
        } else if e[1] > 0 {
            1
        } else {
            2
        };
        let mut lower = e;
        lower[a] -= 1;
        parent[n] = monomial_index(lower) as u32;
        axis[n] = a as u32;
        n += 1;
    }
    (parent, axis)
}

/// How many monomials have degree at most `d`, for `d` = 0..=4: they come first in
/// [`EXPONENTS`], so a product with a monomial of degree `4 - d` ranges over that prefix.
const UP_TO_DEGREE: [usize; MAX_DEGREE + 1] = {
    let mut out = [0; MAX_DEGREE + 1];
    let mut n = 0;
    while n < MOMENT_COUNT {
        let mut d = DEGREE[n] as usize;
        while d <= MAX_DEGREE {
            out[d] += 1;
            d += 1;
        }
        n += 1;
    }
    out
};

/// Per pair of monomials whose degrees sum to at most 4, the index of their product
/// (`u8::MAX` for the others): [`Poly::mul`]'s lookup instead of a search of [`EXPONENTS`].
const PRODUCT: [[u8; MOMENT_COUNT]; MOMENT_COUNT] = products();

const fn products() -> [[u8; MOMENT_COUNT]; MOMENT_COUNT] {
    let mut out = [[u8::MAX; MOMENT_COUNT]; MOMENT_COUNT];
    let mut a = 0;
    while a < MOMENT_COUNT {
        let mut b = 0;
        while b < MOMENT_COUNT {
            let (ea, eb) = (EXPONENTS[a], EXPONENTS[b]);
            let e = [ea[0] + eb[0], ea[1] + eb[1], ea[2] + eb[2]];
            if (e[0] + e[1] + e[2]) as usize <= MAX_DEGREE {
                out[a][b] = monomial_index(e) as u8;
            }
            b += 1;
        }
        a += 1;
    }
    out
}

/// Degree of the monomial at index `n`.
pub fn degree(n: usize) -> usize {
    DEGREE[n] as usize
}

/// [`degree`] of each monomial.
const DEGREE: [u8; MOMENT_COUNT] = {
    let mut out = [0u8; MOMENT_COUNT];
    let mut n = 0;
    while n < MOMENT_COUNT {
        out[n] = EXPONENTS[n][0] + EXPONENTS[n][1] + EXPONENTS[n][2];
        n += 1;
    }
    out
};

/// A polynomial of degree <= 4 in `(dx, dy, dz)`, coefficients in [`EXPONENTS`] order.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Poly(pub [f64; MOMENT_COUNT]);

impl Poly {
    pub fn constant(c: f64) -> Self {
        let mut p = [0.0; MOMENT_COUNT];
        p[0] = c;
        Self(p)
    }

    /// The linear form `v . d`.
    pub fn linear(v: &Vector3<f64>) -> Self {
        let mut p = [0.0; MOMENT_COUNT];
        p[1] = v.x;
        p[2] = v.y;
        p[3] = v.z;
        Self(p)
    }

    /// Product, dropping terms above degree 4 (callers only form products of degree <= 4).
    pub fn mul(&self, other: &Poly) -> Poly {
        let mut out = [0.0; MOMENT_COUNT];
        for (a, &ca) in self.0.iter().enumerate() {
            if ca == 0.0 {
                continue;
            }
            // The monomials `b` whose product with `a` has degree <= 4: a prefix.
            let fits = UP_TO_DEGREE[MAX_DEGREE - degree(a)];
            for (&cb, &ab) in other.0[..fits].iter().zip(&PRODUCT[a][..fits]) {
                if cb != 0.0 {
                    out[usize::from(ab)] += ca * cb;
                }
            }
        }
        Poly(out)
    }

    pub fn add(&self, other: &Poly) -> Poly {
        Poly(std::array::from_fn(|n| self.0[n] + other.0[n]))
    }

    pub fn scale(&self, s: f64) -> Poly {
        Poly(self.0.map(|c| c * s))
    }
}

/// Sums of the monomials (degree <= 4) of `d = p - origin` over a point set, metres^degree.
/// `sums[0]` is the point count.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Moments {
    pub origin: Point3<f64>,
    pub sums: [f64; MOMENT_COUNT],
}

impl Moments {
    pub fn zero(origin: Point3<f64>) -> Self {
        Self {
            origin,
            sums: [0.0; MOMENT_COUNT],
        }
    }

    /// Direct f64 accumulation over `points` (the reference the fixed-point paths are tested
    /// against, and the path for point sets that never go to the GPU).
    pub fn from_points<'a>(
        origin: Point3<f64>,
        points: impl IntoIterator<Item = &'a Point3<f64>>,
    ) -> Self {
        let mut m = Self::zero(origin);
        for p in points {
            m.push(&(p - origin));
        }
        m
    }

    /// Adds one offset `d = p - origin`.
    pub fn push(&mut self, d: &Vector3<f64>) {
        let mut mono = [0.0; MOMENT_COUNT];
        mono[0] = 1.0;
        for n in 1..MOMENT_COUNT {
            mono[n] = mono[PARENT[n] as usize] * d[AXIS[n] as usize];
        }
        for (s, m) in self.sums.iter_mut().zip(mono) {
            *s += m;
        }
    }

    /// Adds another set's moments (same origin).
    pub fn merge(&mut self, other: &Moments) {
        debug_assert_eq!(self.origin, other.origin);
        for (s, o) in self.sums.iter_mut().zip(other.sums) {
            *s += o;
        }
    }

    pub fn count(&self) -> f64 {
        self.sums[0]
    }

    /// Sum over the points of `poly(d)`.
    pub fn sum_of(&self, poly: &Poly) -> f64 {
        poly.0.iter().zip(self.sums).map(|(c, s)| c * s).sum()
    }

    /// Mean offset from the origin (NaN-free only for a non-empty set).
    pub fn mean_offset(&self) -> Vector3<f64> {
        Vector3::new(self.sums[1], self.sums[2], self.sums[3]) / self.count()
    }

    pub fn mean(&self) -> Point3<f64> {
        self.origin + self.mean_offset()
    }

    /// Mean squared distance of the points from the origin.
    pub fn mean_squared_distance(&self) -> f64 {
        (self.sums[4] + self.sums[7] + self.sums[9]) / self.count()
    }

    /// Population covariance (divided by N) of the points.
    pub fn covariance(&self) -> Matrix3<f64> {
        let n = self.count();
        let s = &self.sums;
        let second = Matrix3::new(s[4], s[5], s[6], s[5], s[7], s[8], s[6], s[8], s[9]) / n;
        let mu = self.mean_offset();
        second - mu * mu.transpose()
    }
}

/// Why a fit has no answer.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum FitError {
    #[error("{count} points: a plane needs at least 3")]
    TooFewPoints { count: u64 },
    #[error(
        "points are collinear or coincident (second/largest eigenvalue {ratio:.3e}): normal undefined"
    )]
    Collinear { ratio: f64 },
    #[error("moments are not finite")]
    NonFinite,
    #[error("the symmetric eigen solver did not converge")]
    EigenFailed,
}

/// Limits that decide when a fit is degenerate.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FitLimits {
    /// A set whose second-largest covariance eigenvalue is at most this fraction of the
    /// largest is collinear (no normal).
    pub collinear_eigen_ratio: f64,
    /// Algebraic circle radii above this fall back to the sphere cut, metres.
    pub max_circle_radius_m: f64,
}

/// Result of [`plane3d`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PlaneFit {
    /// Mean of the points.
    pub centroid_m: Point3<f64>,
    /// Unit normal (sign arbitrary; Alg. 2 orients it by eq. 2).
    pub normal: Unit<Vector3<f64>>,
    /// Covariance eigenvalues, ascending, m^2.
    pub eigenvalues_m2: [f64; 3],
}

impl PlaneFit {
    /// PCL's surface variation `l0 / (l0 + l1 + l2)`.
    pub fn curvature(&self) -> f64 {
        let [l0, l1, l2] = self.eigenvalues_m2;
        let total = l0 + l1 + l2;
        if total > 0.0 {
            l0.max(0.0) / total
        } else {
            0.0
        }
    }

    /// RMS distance of the points from the plane.
    pub fn residual_rms_m(&self) -> f64 {
        self.eigenvalues_m2[0].max(0.0).sqrt()
    }
}

/// `plane3d` of Alg. 2: centroid and least-squares normal of the moments' point set.
pub fn plane3d(m: &Moments, limits: &FitLimits) -> Result<PlaneFit, FitError> {
    if !m.sums.iter().all(|s| s.is_finite()) {
        return Err(FitError::NonFinite);
    }
    let count = m.count();
    if count < 3.0 {
        return Err(FitError::TooFewPoints {
            count: count as u64,
        });
    }
    let cov = m.covariance();
    let eig = SymmetricEigen::try_new(cov, f64::EPSILON, 10_000).ok_or(FitError::EigenFailed)?;
    let mut order = [0usize, 1, 2];
    order.sort_by(|&a, &b| eig.eigenvalues[a].total_cmp(&eig.eigenvalues[b]));
    let eigenvalues_m2 = order.map(|i| eig.eigenvalues[i]);
    let [_, l1, l2] = eigenvalues_m2;
    if l1 <= limits.collinear_eigen_ratio * l2 || l2 <= 0.0 {
        let ratio = if l2 > 0.0 { l1 / l2 } else { 0.0 };
        return Err(FitError::Collinear { ratio });
    }
    let normal = eig.eigenvectors.column(order[0]).into_owned();
    if !normal.iter().all(|c| c.is_finite()) {
        return Err(FitError::NonFinite);
    }
    Ok(PlaneFit {
        centroid_m: m.mean(),
        normal: Unit::new_normalize(normal),
        eigenvalues_m2,
    })
}

/// The circle-centre estimator of `circle3d` (config `circle_method`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CircleMethod {
    /// Algebraic least squares (Kasa 1976): cheapest, biased on short arcs.
    Kasa,
    /// Taubin's gradient-weighted algebraic fit (Chernov's Newton solution): near-unbiased.
    #[default]
    Taubin,
    /// Closed form: the fitted plane cut by the sphere around the origin (origin projected onto
    /// the plane). Second moments only.
    SphereCut,
}

impl CircleMethod {
    pub const ALL: [CircleMethod; 3] = [
        CircleMethod::Kasa,
        CircleMethod::Taubin,
        CircleMethod::SphereCut,
    ];

    pub fn name(self) -> &'static str {
        match self {
            CircleMethod::Kasa => "kasa",
            CircleMethod::Taubin => "taubin",
            CircleMethod::SphereCut => "sphere_cut",
        }
    }
}

/// Result of [`circle3d`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CircleFit {
    pub center_m: Point3<f64>,
    /// Normal of the circle's plane (sign arbitrary).
    pub normal: Unit<Vector3<f64>>,
    pub radius_m: f64,
    /// RMS distance of the points from the circle (in-plane algebraic distance scaled to
    /// geometric, combined with the out-of-plane residual).
    pub residual_rms_m: f64,
    /// The plane the circle lies in.
    pub plane: PlaneFit,
    /// True when the requested algebraic method was degenerate (straight arc) and the sphere
    /// cut answered instead.
    pub fell_back: bool,
}

/// Central planar moments `M_pq = mean (u - u_mean)^p (v - v_mean)^q`, p + q <= 4.
struct PlanarMoments {
    mean: [f64; 2],
    m: [[f64; 5]; 5],
}

fn binomial(n: usize, k: usize) -> f64 {
    (0..k).fold(1.0, |acc, i| acc * (n - i) as f64 / (i + 1) as f64)
}

// Index arithmetic over the binomial expansion reads clearer than iterator chains.
#[allow(clippy::needless_range_loop)]
fn planar_moments(m: &Moments, e1: &Vector3<f64>, e2: &Vector3<f64>) -> PlanarMoments {
    let n = m.count();
    let (u, v) = (Poly::linear(e1), Poly::linear(e2));
    let mut upow = [Poly::constant(1.0); 5];
    let mut vpow = [Poly::constant(1.0); 5];
    for k in 1..5 {
        upow[k] = upow[k - 1].mul(&u);
        vpow[k] = vpow[k - 1].mul(&v);
    }
    let mut raw = [[0.0; 5]; 5];
    for p in 0..5 {
        for q in 0..5 - p {
            raw[p][q] = m.sum_of(&upow[p].mul(&vpow[q])) / n;
        }
    }
    let (mu, mv) = (raw[1][0], raw[0][1]);
    let mut central = [[0.0; 5]; 5];
    for p in 0..5 {
        for q in 0..5 - p {
            let mut acc = 0.0;
            for a in 0..=p {
                for b in 0..=q {
                    acc += binomial(p, a)
                        * binomial(q, b)
                        * (-mu).powi((p - a) as i32)
                        * (-mv).powi((q - b) as i32)
                        * raw[a][b];
                }
            }
            central[p][q] = acc;
        }
    }
    central[1][0] = 0.0;
    central[0][1] = 0.0;
    PlanarMoments {
        mean: [mu, mv],
        m: central,
    }
}

/// `circle3d` of Alg. 2 with the chosen centre estimator.
pub fn circle3d(
    m: &Moments,
    method: CircleMethod,
    limits: &FitLimits,
) -> Result<CircleFit, FitError> {
    let plane = plane3d(m, limits)?;
    let n = plane.normal.into_inner();
    let offset = n.dot(&(plane.centroid_m - m.origin));
    let sphere_cut = || {
        let radius2 = m.mean_squared_distance() - offset * offset - plane.eigenvalues_m2[0];
        let radius_m = radius2.max(0.0).sqrt();
        CircleFit {
            center_m: m.origin + offset * n,
            normal: plane.normal,
            radius_m,
            residual_rms_m: sphere_cut_residual(m, &plane, radius_m),
            plane,
            fell_back: false,
        }
    };
    if method == CircleMethod::SphereCut {
        return Ok(sphere_cut());
    }
    // Rodrigues rotation taking the normal onto z; its rows are the in-plane axes.
    let rot = Rotation3::rotation_between(&n, &Vector3::z())
        .unwrap_or_else(|| Rotation3::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI));
    let e1 = rot.matrix().row(0).transpose();
    let e2 = rot.matrix().row(1).transpose();
    let pm = planar_moments(m, &e1, &e2);
    let c = &pm.m;
    // Normalise by the RMS planar spread so the Newton iteration works on O(1) numbers.
    let scale2 = c[2][0] + c[0][2];
    if !scale2.is_finite() || scale2 <= 0.0 {
        return Ok(CircleFit {
            fell_back: true,
            ..sphere_cut()
        });
    }
    let s = scale2.sqrt();
    let (mxx, myy, mxy) = (c[2][0] / scale2, c[0][2] / scale2, c[1][1] / scale2);
    let s3 = scale2 * s;
    let (mxz, myz) = ((c[3][0] + c[1][2]) / s3, (c[2][1] + c[0][3]) / s3);
    let mzz = (c[4][0] + 2.0 * c[2][2] + c[0][4]) / (scale2 * scale2);
    let mz = mxx + myy;
    let cov_xy = mxx * myy - mxy * mxy;
    let root = match method {
        CircleMethod::Kasa => 0.0,
        _ => taubin_root(mxx, myy, mxy, mxz, myz, mzz),
    };
    let det = root * root - root * mz + cov_xy;
    let xc = (mxz * (myy - root) - myz * mxy) / det / 2.0;
    let yc = (myz * (mxx - root) - mxz * mxy) / det / 2.0;
    let radius = (xc * xc + yc * yc + mz).sqrt();
    let radius_m = radius * s;
    if !(radius_m.is_finite() && xc.is_finite() && yc.is_finite())
        || radius_m > limits.max_circle_radius_m
    {
        return Ok(CircleFit {
            fell_back: true,
            ..sphere_cut()
        });
    }
    // Algebraic residual mean(f^2), f = |q - c|^2 - R^2 over centred planar coordinates.
    let k = xc * xc + yc * yc - radius * radius;
    let alg = mzz + 4.0 * xc * xc * mxx + 4.0 * yc * yc * myy + 8.0 * xc * yc * mxy
        - 4.0 * xc * mxz
        - 4.0 * yc * myz
        + 2.0 * k * mz
        + k * k;
    let in_plane2 = (alg.max(0.0) / (4.0 * radius * radius)) * scale2;
    let center_m = m.origin + (pm.mean[0] + xc * s) * e1 + (pm.mean[1] + yc * s) * e2 + offset * n;
    Ok(CircleFit {
        center_m,
        normal: plane.normal,
        radius_m,
        residual_rms_m: (in_plane2 + plane.eigenvalues_m2[0].max(0.0)).sqrt(),
        plane,
        fell_back: false,
    })
}

/// Root of Taubin's characteristic polynomial by Newton from 0 (Chernov, "Circular and linear
/// regression", 2010, CircleFitByTaubin), on centred, normalised moments.
fn taubin_root(mxx: f64, myy: f64, mxy: f64, mxz: f64, myz: f64, mzz: f64) -> f64 {
    let mz = mxx + myy;
    let cov_xy = mxx * myy - mxy * mxy;
    let var_z = mzz - mz * mz;
    let a3 = 4.0 * mz;
    let a2 = -3.0 * mz * mz - mzz;
    let a1 = var_z * mz + 4.0 * cov_xy * mz - mxz * mxz - myz * myz;
    let a0 = mxz * (mxz * myy - myz * mxy) + myz * (myz * mxx - mxz * mxy) - var_z * cov_xy;
    let (a22, a33) = (2.0 * a2, 3.0 * a3);
    let (mut x, mut y) = (0.0f64, a0);
    for _ in 0..100 {
        let dy = a1 + x * (a22 + a33 * x);
        let x_new = x - y / dy;
        if x_new == x || !x_new.is_finite() {
            break;
        }
        let y_new = a0 + x_new * (a1 + x_new * (a2 + x_new * a3));
        if y_new.abs() >= y.abs() {
            break;
        }
        x = x_new;
        y = y_new;
    }
    x
}

/// RMS distance from the sphere-cut circle: mean((|d - t n|^2 - rho^2)^2) / (4 rho^2) from the
/// fourth moments, plus the out-of-plane variance.
fn sphere_cut_residual(m: &Moments, plane: &PlaneFit, radius_m: f64) -> f64 {
    let n = plane.normal.into_inner();
    let out_of_plane = plane.eigenvalues_m2[0].max(0.0);
    if radius_m <= 0.0 {
        return out_of_plane.sqrt();
    }
    // f(d) = |d|^2 - (n.d)^2 - rho^2 (in-plane squared distance from the centre on the axis).
    let sq = Poly::linear(&Vector3::x())
        .mul(&Poly::linear(&Vector3::x()))
        .add(&Poly::linear(&Vector3::y()).mul(&Poly::linear(&Vector3::y())))
        .add(&Poly::linear(&Vector3::z()).mul(&Poly::linear(&Vector3::z())));
    let nd = Poly::linear(&n);
    let f = sq
        .add(&nd.mul(&nd).scale(-1.0))
        .add(&Poly::constant(-(radius_m * radius_m)));
    let alg = m.sum_of(&f.mul(&f)) / m.count();
    (alg.max(0.0) / (4.0 * radius_m * radius_m) + out_of_plane).sqrt()
}

/// Result of [`height_field`]: the surface `z = f(x, y)` in a frame at the moments' origin,
/// `x, y` along `e1, e2` and `z` along `axis` (into the surface), and its point closest to the
/// origin.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HeightField {
    /// `f = c0 + c1 x + c2 y + c3 x^2 + c4 x y + c5 y^2`, metres.
    pub coefficients: [f64; 6],
    /// The point of the surface closest to the origin.
    pub closest_m: Point3<f64>,
    /// Unit surface normal there, pointing to the origin's side (against `axis`).
    pub normal: Unit<Vector3<f64>>,
    /// RMS of `z - f(x, y)` over the points, metres.
    pub residual_rms_m: f64,
    /// Standard error of `closest_m` from the points' scatter about the field (the
    /// coefficients' least-squares covariance carried through the closest point), metres;
    /// infinite when the fit cannot tell.
    pub closest_se_m: f64,
    /// Whether the quadratic terms are kept ([`height_field`]): false for a plane.
    pub curved: bool,
    /// F statistic of the quadratic terms against the plane in this field's frame
    /// ([`height_field`]); 0 where the points do not span them.
    pub curvature_f: f64,
    /// The frame's `z` axis (`x, y` follow from it as in the fit).
    pub axis: Unit<Vector3<f64>>,
}

impl HeightField {
    /// RMS of `z - f(x, y)` over another point set given by its moments (same origin),
    /// metres: how far that set lies from this surface. `None` for an empty or non-finite
    /// set.
    pub fn residual_rms_of(&self, m: &Moments) -> Option<f64> {
        let count = m.count();
        if !(count > 0.0 && m.sums.iter().all(|s| s.is_finite())) {
            return None;
        }
        let (e1, e2) = tangent_frame(&self.axis);
        let (x, y) = (Poly::linear(&e1), Poly::linear(&e2));
        let c = self.coefficients;
        let f = Poly::constant(c[0])
            .add(&x.scale(c[1]))
            .add(&y.scale(c[2]))
            .add(&x.mul(&x).scale(c[3]))
            .add(&x.mul(&y).scale(c[4]))
            .add(&y.mul(&y).scale(c[5]));
        let residual = Poly::linear(&self.axis.into_inner()).add(&f.scale(-1.0));
        Some((m.sum_of(&residual.mul(&residual)).max(0.0) / count).sqrt())
    }
}

/// The tangent directions `x, y` of a height field over the plane perpendicular to `axis`.
fn tangent_frame(axis: &Unit<Vector3<f64>>) -> (Vector3<f64>, Vector3<f64>) {
    let rot = Rotation3::rotation_between(axis, &Vector3::z())
        .unwrap_or_else(|| Rotation3::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI));
    (
        rot.matrix().row(0).transpose(),
        rot.matrix().row(1).transpose(),
    )
}

/// Least-squares quadratic height field `z = f(x, y)` of the moments' point set over the
/// plane through the origin perpendicular to `axis`, and Newton's closest point of it to the
/// origin. The normal equations need the sums of products of `{1, x, y, x^2, xy, y^2}` and
/// `z`: monomials of degree <= 4, all in [`Moments`]. Unlike a plane through a ring cut by a
/// sphere, this stays right on a surface whose curvature differs between directions (a
/// forearm: a cylinder) when only part of the ring is visible. Coordinates are scaled by
/// `scale_m` (the point set's extent) so the 6x6 system is well conditioned. `m` may be
/// weighted; `point_count` is the number of points behind it (for the standard error).
///
/// The quadratic terms are kept only where they explain the points better than the plane
/// `z = c0 + c1 x + c2 y` (the nested fit): when the F statistic of the three extra terms,
/// `((RSS_plane - RSS_quadric) / 3) / (RSS_quadric / (N - 6))`, exceeds `min_curvature_f`.
/// Otherwise (a flat patch, or points that do not span the quadratic, such as one ring) the
/// plane is the field: its closest point is the origin's foot on it, however little of the
/// patch the camera sees, where a quadric fitted to the noise of a partial patch bends it.
pub fn height_field(
    m: &Moments,
    point_count: f64,
    axis: &Unit<Vector3<f64>>,
    scale_m: f64,
    min_curvature_f: f64,
) -> Result<HeightField, FitError> {
    if !(m.sums.iter().all(|s| s.is_finite()) && scale_m.is_finite() && scale_m > 0.0) {
        return Err(FitError::NonFinite);
    }
    let count = m.count();
    if count < 6.0 {
        return Err(FitError::TooFewPoints {
            count: count.max(0.0) as u64,
        });
    }
    let (e1, e2) = tangent_frame(axis);
    let inv = 1.0 / scale_m;
    let (x, y) = (Poly::linear(&(e1 * inv)), Poly::linear(&(e2 * inv)));
    let z = Poly::linear(&(axis.into_inner() * inv));
    let basis = [Poly::constant(1.0), x, y, x.mul(&x), x.mul(&y), y.mul(&y)];
    let mut ata = nalgebra::Matrix6::<f64>::zeros();
    let mut atz = nalgebra::Vector6::<f64>::zeros();
    for i in 0..6 {
        for j in i..6 {
            let v = m.sum_of(&basis[i].mul(&basis[j]));
            ata[(i, j)] = v;
            ata[(j, i)] = v;
        }
        atz[i] = m.sum_of(&basis[i].mul(&z));
    }
    let zz = m.sum_of(&z.mul(&z));
    let plane = nested_fit::<3>(&ata, &atz, zz, count).ok_or(FitError::Collinear { ratio: 0.0 })?;
    let quadric = nested_fit::<6>(&ata, &atz, zz, count).filter(|_| point_count > 6.0);
    let curvature_f = quadric.as_ref().map_or(0.0, |q| {
        // 0 / 0 (points exactly on both) is no evidence of curvature.
        ((plane.rss - q.rss) * (point_count - 6.0) / (3.0 * q.rss)).max(0.0)
    });
    let fit = match quadric {
        Some(quadric)
            if (plane.rss - quadric.rss) * (point_count - 6.0)
                > min_curvature_f * 3.0 * quadric.rss =>
        {
            quadric
        }
        _ => plane,
    };
    let c = fit.coefficients;
    let residual2 = fit.rss / count;
    let (u, v) = closest_on(&c)?;
    let closest_se_m =
        closest_standard_error(&fit, point_count).map_or(f64::INFINITY, |se| se * scale_m);
    let fz = quadric_height(&c, u, v);
    let (fu, fv) = quadric_slope(&c, u, v);
    let closest_m = m.origin + scale_m * (u * e1 + v * e2 + fz * axis.into_inner());
    let normal =
        Unit::try_new(fu * e1 + fv * e2 - axis.into_inner(), 1e-12).ok_or(FitError::NonFinite)?;
    Ok(HeightField {
        coefficients: [
            c[0] * scale_m,
            c[1],
            c[2],
            c[3] / scale_m,
            c[4] / scale_m,
            c[5] / scale_m,
        ],
        closest_m,
        normal,
        residual_rms_m: residual2.sqrt() * scale_m,
        closest_se_m,
        curved: fit.terms == 6,
        curvature_f,
        axis: *axis,
    })
}

/// Least squares over the first `K` terms of the height field's basis (3: the plane, 6: the
/// quadric), in scaled units: coefficients (the rest zero), the inverse of their normal
/// matrix (zero outside `K x K`) and the residual sum of squares.
struct NestedFit {
    terms: usize,
    coefficients: nalgebra::Vector6<f64>,
    normal_inverse: nalgebra::Matrix6<f64>,
    rss: f64,
}

/// [`NestedFit`] of the first `K` terms; `None` when the points do not span them.
fn nested_fit<const K: usize>(
    ata: &nalgebra::Matrix6<f64>,
    atz: &nalgebra::Vector6<f64>,
    zz: f64,
    count: f64,
) -> Option<NestedFit> {
    let a = ata.fixed_view::<K, K>(0, 0).into_owned();
    let b = atz.fixed_rows::<K>(0).into_owned();
    let chol = nalgebra::Cholesky::new(a)?;
    // Scaled coordinates are O(1): a pivot this small means the points do not span the
    // terms (a single ring for the quadric, a line for the plane).
    let diag_min = (0..K)
        .map(|i| chol.l_dirty()[(i, i)])
        .fold(f64::INFINITY, f64::min);
    if diag_min.is_nan() || diag_min <= 1e-6 * count.sqrt() {
        return None;
    }
    let c = chol.solve(&b);
    let mut coefficients = nalgebra::Vector6::zeros();
    coefficients.fixed_rows_mut::<K>(0).copy_from(&c);
    let mut normal_inverse = nalgebra::Matrix6::zeros();
    normal_inverse
        .fixed_view_mut::<K, K>(0, 0)
        .copy_from(&chol.inverse());
    Some(NestedFit {
        terms: K,
        coefficients,
        normal_inverse,
        rss: (zz - c.dot(&b)).max(0.0),
    })
}

/// Closest point `(u, v, f(u, v))` of the height field with coefficients `c` (scaled units)
/// to the origin: Newton on the gradient of `x^2 + y^2 + f^2`, from the foot of the axis.
fn closest_on(c: &nalgebra::Vector6<f64>) -> Result<(f64, f64), FitError> {
    let (mut u, mut v) = (0.0f64, 0.0f64);
    for _ in 0..20 {
        let fz = quadric_height(c, u, v);
        let (fu, fv) = quadric_slope(c, u, v);
        let g = nalgebra::Vector2::new(u + fz * fu, v + fz * fv);
        let h = nalgebra::Matrix2::new(
            1.0 + fu * fu + fz * 2.0 * c[3],
            fu * fv + fz * c[4],
            fu * fv + fz * c[4],
            1.0 + fv * fv + fz * 2.0 * c[5],
        );
        let Some(step) = h.try_inverse().map(|hi| hi * g) else {
            return Err(FitError::EigenFailed);
        };
        u -= step.x;
        v -= step.y;
        if !(u.is_finite() && v.is_finite()) || u.abs() > 1.0 || v.abs() > 1.0 {
            return Err(FitError::NonFinite);
        }
        if step.norm() < 1e-12 {
            break;
        }
    }
    Ok((u, v))
}

/// `f(u, v) = c0 + c1 u + c2 v + c3 u^2 + c4 u v + c5 v^2`.
fn quadric_height(c: &nalgebra::Vector6<f64>, u: f64, v: f64) -> f64 {
    c[0] + c[1] * u + c[2] * v + c[3] * u * u + c[4] * u * v + c[5] * v * v
}

/// `(df/du, df/dv)` of [`quadric_height`].
fn quadric_slope(c: &nalgebra::Vector6<f64>, u: f64, v: f64) -> (f64, f64) {
    (
        c[1] + 2.0 * c[3] * u + c[4] * v,
        c[2] + c[4] * u + 2.0 * c[5] * v,
    )
}

/// Standard error of the closest point (scaled units): the coefficients' covariance
/// `s^2 w (A^T W A)^-1` (`s^2` the unbiased residual variance over `points` points, `w`
/// their mean weight: together the weighted residual sum of squares over `points - terms`)
/// carried through the closest point's Jacobian, taken by central differences of
/// [`closest_on`]. `None` when the fit leaves no degree of freedom or a perturbed field has
/// no closest point.
fn closest_standard_error(fit: &NestedFit, points: f64) -> Option<f64> {
    let terms = fit.terms as f64;
    if points.is_nan() || points <= terms {
        return None;
    }
    let covariance = fit.normal_inverse * (fit.rss / (points - terms));
    let c = &fit.coefficients;
    let point = |c: &nalgebra::Vector6<f64>| -> Option<Vector3<f64>> {
        let (u, v) = closest_on(c).ok()?;
        Some(Vector3::new(u, v, quadric_height(c, u, v)))
    };
    let mut jacobian = nalgebra::Matrix3x6::<f64>::zeros();
    for k in 0..fit.terms {
        let h = 1e-6 * (1.0 + c[k].abs());
        let mut up = *c;
        let mut down = *c;
        up[k] += h;
        down[k] -= h;
        jacobian.set_column(k, &((point(&up)? - point(&down)?) / (2.0 * h)));
    }
    let se2 = (jacobian * covariance * jacobian.transpose()).trace();
    (se2.is_finite() && se2 >= 0.0).then(|| se2.sqrt())
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    const LIMITS: FitLimits = FitLimits {
        collinear_eigen_ratio: 1e-10,
        max_circle_radius_m: 10.0,
    };

    #[test]
    fn tables_are_consistent() {
        assert_eq!(EXPONENTS[0], [0, 0, 0]);
        assert_eq!(EXPONENTS[1], [1, 0, 0]);
        assert_eq!(EXPONENTS[4], [2, 0, 0]);
        assert_eq!(EXPONENTS[7], [0, 2, 0]);
        assert_eq!(EXPONENTS[9], [0, 0, 2]);
        assert_eq!(EXPONENTS[34], [0, 0, 4]);
        for n in 1..MOMENT_COUNT {
            let mut e = EXPONENTS[PARENT[n] as usize];
            e[AXIS[n] as usize] += 1;
            assert_eq!(e, EXPONENTS[n]);
            assert!((PARENT[n] as usize) < n);
        }
        for a in 0..MOMENT_COUNT {
            assert_eq!(
                usize::from(DEGREE[a]),
                EXPONENTS[a].iter().map(|&e| usize::from(e)).sum::<usize>()
            );
            for b in 0..MOMENT_COUNT {
                let (ea, eb) = (EXPONENTS[a], EXPONENTS[b]);
                let e = [ea[0] + eb[0], ea[1] + eb[1], ea[2] + eb[2]];
                match PRODUCT[a][b] {
                    u8::MAX => assert!(degree(a) + degree(b) > MAX_DEGREE),
                    ab => assert_eq!(EXPONENTS[usize::from(ab)], e),
                }
                assert_eq!(
                    b < UP_TO_DEGREE[MAX_DEGREE - degree(a).min(MAX_DEGREE)],
                    degree(a) + degree(b) <= MAX_DEGREE
                );
            }
        }
    }

    /// `Poly::mul` term by term in the order of the two polynomials' indices, the product's
    /// index searched in `EXPONENTS`: the definition the table-driven product must equal bit
    /// for bit (zero, negative zero and non-finite coefficients included).
    #[test]
    fn the_product_equals_its_definition_bit_for_bit() {
        let definition = |p: &Poly, q: &Poly| {
            let mut out = [0.0; MOMENT_COUNT];
            for (a, &ca) in p.0.iter().enumerate() {
                for (b, &cb) in q.0.iter().enumerate() {
                    if ca != 0.0 && cb != 0.0 && degree(a) + degree(b) <= MAX_DEGREE {
                        let (ea, eb) = (EXPONENTS[a], EXPONENTS[b]);
                        out[monomial_index([ea[0] + eb[0], ea[1] + eb[1], ea[2] + eb[2]])] +=
                            ca * cb;
                    }
                }
            }
            Poly(out)
        };
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let special = [0.0, -0.0, f64::INFINITY, f64::NAN, 1e300];
        for _ in 0..500 {
            let mut poly = || {
                Poly(std::array::from_fn(|_| match rng.random_range(0..8) {
                    0..3 => 0.0,
                    3 => special[rng.random_range(0..special.len())],
                    _ => rng.random::<f64>() - 0.5,
                }))
            };
            let (p, q) = (poly(), poly());
            let bits = |p: Poly| p.0.map(f64::to_bits);
            assert_eq!(bits(p.mul(&q)), bits(definition(&p, &q)));
        }
    }

    fn moments(origin: Point3<f64>, pts: &[Point3<f64>]) -> Moments {
        Moments::from_points(origin, pts)
    }

    /// Points of a circle arc of `radius` around `center` in the plane with normal `n`.
    fn arc(
        center: Point3<f64>,
        n: Vector3<f64>,
        radius: f64,
        from: f64,
        to: f64,
        count: usize,
        noise: f64,
    ) -> Vec<Point3<f64>> {
        let n = n.normalize();
        let e1 = n.cross(&Vector3::new(0.3, 0.5, 0.7)).normalize();
        let e2 = n.cross(&e1);
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        (0..count)
            .map(|i| {
                let t = from + (to - from) * i as f64 / (count - 1) as f64;
                let r = radius + noise * (rng.random::<f64>() - 0.5);
                center + r * (t.cos() * e1 + t.sin() * e2)
            })
            .collect()
    }

    #[test]
    fn plane_normal_of_a_tilted_disc() {
        let n = Vector3::new(0.2, -0.4, 0.9).normalize();
        let pts = arc(Point3::new(1.0, 2.0, 3.0), n, 0.05, 0.0, 6.0, 200, 0.02);
        let fit = plane3d(&moments(Point3::new(1.0, 2.0, 3.05), &pts), &LIMITS).unwrap();
        assert!(fit.normal.dot(&n).abs() > 1.0 - 1e-12);
        assert!(fit.residual_rms_m() < 1e-9);
    }

    #[test]
    fn circle_methods_recover_a_full_circle() {
        let n = Vector3::new(0.0, 0.3, 1.0);
        let center = Point3::new(0.1, -0.2, 0.5);
        let pts = arc(center, n, 0.04, 0.0, 6.2, 300, 0.0);
        let origin = center + 0.03 * n.normalize();
        for method in CircleMethod::ALL {
            let fit = circle3d(&moments(origin, &pts), method, &LIMITS).unwrap();
            assert!(
                (fit.center_m - center).norm() < 1e-9,
                "{method:?} {:?}",
                fit.center_m
            );
            assert!(
                (fit.radius_m - 0.04).abs() < 2e-3,
                "{method:?} {}",
                fit.radius_m
            );
            assert!(!fit.fell_back);
        }
    }

    #[test]
    fn taubin_beats_kasa_on_a_noisy_short_arc() {
        let n = Vector3::z();
        let center = Point3::new(0.0, 0.0, 0.0);
        let pts = arc(center, n, 0.05, 0.0, 1.2, 400, 0.004);
        let origin = Point3::new(0.0, 0.0, 0.0);
        let kasa = circle3d(&moments(origin, &pts), CircleMethod::Kasa, &LIMITS).unwrap();
        let taubin = circle3d(&moments(origin, &pts), CircleMethod::Taubin, &LIMITS).unwrap();
        let (ek, et) = ((kasa.radius_m - 0.05).abs(), (taubin.radius_m - 0.05).abs());
        assert!(et < ek, "taubin {et} kasa {ek}");
        assert!(et < 1e-3);
    }

    #[test]
    fn straight_arc_falls_back_to_the_sphere_cut() {
        use std::f64::consts::FRAC_PI_2;
        // A 1 cm piece of a 1 km circle: numerically a straight segment with a tiny thickness.
        let n = Vector3::z();
        let mut pts = arc(
            Point3::new(0.0, -1000.0, 0.0),
            n,
            1000.0,
            FRAC_PI_2 - 5e-5,
            FRAC_PI_2 + 5e-5,
            50,
            0.0,
        );
        pts.extend(arc(
            Point3::new(0.0, -1000.0, 0.001),
            n,
            1000.0,
            FRAC_PI_2 - 5e-5,
            FRAC_PI_2 + 5e-5,
            50,
            0.0,
        ));
        let limits = FitLimits {
            max_circle_radius_m: 1.0,
            ..LIMITS
        };
        let fit = circle3d(
            &moments(Point3::new(0.0, 0.0, 0.0), &pts),
            CircleMethod::Taubin,
            &limits,
        )
        .unwrap();
        assert!(fit.fell_back);
        assert!(fit.center_m.coords.iter().all(|c| c.is_finite()));
    }

    #[test]
    fn degenerate_sets_are_reported() {
        let o = Point3::origin();
        let two = [Point3::new(1.0, 0.0, 0.0), Point3::new(0.0, 1.0, 0.0)];
        assert!(matches!(
            plane3d(&moments(o, &two), &LIMITS),
            Err(FitError::TooFewPoints { count: 2 })
        ));
        let line: Vec<_> = (0..10)
            .map(|i| Point3::new(i as f64 * 0.01, i as f64 * 0.02, 0.0))
            .collect();
        assert!(matches!(
            plane3d(&moments(o, &line), &LIMITS),
            Err(FitError::Collinear { .. })
        ));
        let same = vec![Point3::new(0.1, 0.2, 0.3); 20];
        assert!(matches!(
            plane3d(&moments(o, &same), &LIMITS),
            Err(FitError::Collinear { .. })
        ));
        let mut nan = moments(o, &line);
        nan.sums[5] = f64::NAN;
        assert_eq!(plane3d(&nan, &LIMITS), Err(FitError::NonFinite));
    }

    /// PCL's test asserts this PCA over all 397 points of bun0.pcd (tolerance 1e-4).
    #[test]
    fn pca_of_bun0_matches_pcl() {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/data/pcl/bun0.pcd");
        let cloud = crate::io::read_cloud(std::path::Path::new(path)).unwrap();
        let pts: Vec<Point3<f64>> = cloud
            .points
            .iter()
            .map(|p| Point3::new(p.x.into(), p.y.into(), p.z.into()))
            .collect();
        // Moments about the first point keep the raw sums small (no cancellation).
        let fit = plane3d(&moments(pts[0], &pts), &LIMITS).unwrap();
        let expected = [0.035592, 0.369596, 0.928511];
        for (got, want) in fit.normal.iter().zip(expected) {
            assert!((got.abs() - want).abs() < 1e-4, "{:?}", fit.normal);
        }
        assert!(
            (fit.curvature() - 0.0693136).abs() < 1e-4,
            "{}",
            fit.curvature()
        );
        let c = fit.centroid_m;
        assert!((c - Point3::new(-0.0290809, 0.102653, 0.027302)).norm() < 1e-6);
    }

    #[test]
    fn height_field_recovers_an_anisotropic_paraboloid_seen_from_one_side() {
        // z = 0.03 + x^2 / (2 * 0.2) + y^2 / (2 * 0.035) along -w: a forearm-like surface,
        // sampled only on one side (y > -0.01), with the frame's axis tilted 12 deg.
        let w = Vector3::new(0.1, -0.2, 1.0).normalize();
        let a = w.cross(&Vector3::x()).normalize();
        let b = w.cross(&a);
        let hip = Point3::new(0.2, -0.4, 1.1);
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let pts: Vec<Point3<f64>> = (0..400)
            .map(|_| {
                let (x, y) = (rng.random_range(-0.05..0.05), rng.random_range(-0.01..0.03));
                let z = 0.03 + x * x / 0.4 + y * y / 0.07;
                hip + x * a + y * b - z * w
            })
            .collect();
        let tilt = Rotation3::from_axis_angle(&Unit::new_normalize(a + b), 12f64.to_radians());
        let axis = Unit::new_normalize(tilt * -w);
        // In the tilted frame the paraboloid is no longer exactly a height field: close.
        let first = height_field(&moments(hip, &pts), pts.len() as f64, &axis, 0.05, 0.0).unwrap();
        assert!(
            (first.closest_m - (hip - 0.03 * w)).norm() < 5e-4,
            "{first:?}"
        );
        assert!(first.normal.angle(&w) < 1f64.to_radians(), "{first:?}");
        // Refitted about its own normal it converges to the exact surface.
        let mut fit = first;
        for _ in 0..4 {
            fit = height_field(
                &moments(hip, &pts),
                pts.len() as f64,
                &-fit.normal,
                0.05,
                0.0,
            )
            .unwrap();
        }
        assert!((fit.closest_m - (hip - 0.03 * w)).norm() < 1e-9, "{fit:?}");
        assert!(fit.normal.angle(&w) < 1e-8, "{fit:?}");
        assert!(fit.residual_rms_m < 1e-7, "{fit:?}");
        // Another point set's distance from the field follows from its moments: on the surface
        // further out, nothing; shifted 4 mm along the normal, 4 mm.
        let further: Vec<Point3<f64>> = (0..50)
            .map(|i| {
                let (x, y) = (0.06, -0.01 + 0.0008 * f64::from(i));
                hip + x * a + y * b - (0.03 + x * x / 0.4 + y * y / 0.07) * w
            })
            .collect();
        let shifted: Vec<Point3<f64>> = further.iter().map(|p| p + 0.004 * w).collect();
        assert!(fit.residual_rms_of(&moments(hip, &further)).unwrap() < 1e-7);
        let off = fit.residual_rms_of(&moments(hip, &shifted)).unwrap();
        assert!((off - 0.004).abs() < 1e-7, "{off}");
        assert_eq!(fit.residual_rms_of(&Moments::zero(hip)), None);
        // A plane through the same one-sided set tilts towards the seen side.
        let plane = plane3d(&moments(hip, &pts), &LIMITS).unwrap();
        assert!(plane.normal.angle(&w).min(plane.normal.angle(&-w)) > 5f64.to_radians());
        assert!(first.curved && fit.curved);
        // A single ring does not span the quadratic: the field is its plane, and the closest
        // point the HIP's foot on it.
        let ring = arc(hip - 0.03 * w, w, 0.02, 0.0, 2.0, 50, 0.0);
        let flat = height_field(
            &moments(hip, &ring),
            ring.len() as f64,
            &Unit::new_normalize(-w),
            0.05,
            0.0,
        )
        .unwrap();
        assert!(!flat.curved, "{flat:?}");
        assert!(
            (flat.closest_m - (hip - 0.03 * w)).norm() < 1e-9,
            "{flat:?}"
        );
    }

    /// A flat patch seen on one side only (the robot's shadow hides the rest) with 2 mm of
    /// noise: the F test keeps the plane, whose closest point is the HIP's foot; a curved
    /// cap with the same noise keeps its curvature.
    #[test]
    fn a_flat_patch_keeps_the_plane_and_a_curved_cap_its_curvature() {
        let hip = Point3::origin();
        let fit_of = |seed: u64, curvature_per_m: f64, min_f: f64| {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let pts: Vec<Point3<f64>> = (0..200)
                .map(|_| {
                    let (x, y) = (rng.random_range(0.02..0.07), rng.random_range(-0.05..0.05));
                    let z = 0.05
                        + 0.5 * curvature_per_m * (x * x + y * y)
                        + 0.002 * rng.random_range(-1.0..1.0);
                    Point3::new(x, y, -z)
                })
                .collect();
            height_field(
                &moments(hip, &pts),
                pts.len() as f64,
                &-Vector3::z_axis(),
                0.1,
                min_f,
            )
            .unwrap()
        };
        let truth = Point3::new(0.0, 0.0, -0.05);
        let mut plane_worst: f64 = 0.0;
        let mut quadric_worst: f64 = 0.0;
        for seed in 0..20 {
            let plane = fit_of(seed, 0.0, 4.0);
            assert!(!plane.curved, "seed {seed}: {plane:?}");
            // The F statistic is the field's own, whichever terms it keeps.
            assert!(plane.curvature_f < 4.0, "seed {seed}: {plane:?}");
            plane_worst = plane_worst.max((plane.closest_m - truth).norm());
            let quadric = fit_of(seed, 0.0, 0.0);
            assert!(quadric.curved);
            quadric_worst = quadric_worst.max((quadric.closest_m - truth).norm());
            // A head-like cap (radius 10 cm) with the same noise and coverage stays curved.
            let cap = fit_of(seed, 10.0, 4.0);
            assert!(
                cap.curved && cap.curvature_f > 100.0,
                "seed {seed}: {cap:?}"
            );
        }
        assert!(plane_worst < 1e-3, "{plane_worst}");
        assert!(
            quadric_worst > 2.0 * plane_worst,
            "{quadric_worst} vs {plane_worst}"
        );
    }

    /// The closest point's standard error agrees with its scatter over noise draws, and
    /// is large where the points leave the field's curvature undetermined.
    #[test]
    fn closest_point_standard_error_matches_the_scatter_over_noise_draws() {
        let hip = Point3::origin();
        // z = 0.06 + (x^2 + y^2) / (2 * 0.15): a chest-like cap 6 cm below the HIP, seen
        // in a disc of 4.5 cm, or in a sliver at one side of it, with 3 mm of noise.
        let draw = |seed: u64, sliver: bool, noise: f64| {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let pts: Vec<Point3<f64>> = (0..150)
                .map(|_| {
                    let (x, y) = if sliver {
                        (rng.random_range(0.03..0.045), rng.random_range(-0.01..0.01))
                    } else {
                        (
                            rng.random_range(-0.045..0.045),
                            rng.random_range(-0.045..0.045),
                        )
                    };
                    let z = 0.06 + (x * x + y * y) / 0.3 + noise * rng.random_range(-1.0..1.0);
                    Point3::new(x, y, -z)
                })
                .collect();
            height_field(
                &moments(hip, &pts),
                pts.len() as f64,
                &-Vector3::z_axis(),
                0.1,
                0.0,
            )
        };
        let uniform = 0.003 * 3f64.sqrt();
        let fits: Vec<HeightField> = (0..300).map(|k| draw(k, false, uniform).unwrap()).collect();
        let mean = fits
            .iter()
            .map(|f| f.closest_m.coords)
            .sum::<Vector3<f64>>()
            / 300.0;
        let scatter = (fits
            .iter()
            .map(|f| (f.closest_m.coords - mean).norm_squared())
            .sum::<f64>()
            / 299.0)
            .sqrt();
        let predicted = fits.iter().map(|f| f.closest_se_m).sum::<f64>() / 300.0;
        assert!(
            (predicted / scatter - 1.0).abs() < 0.2,
            "predicted {predicted}, scatter {scatter}"
        );
        assert!((mean - Vector3::new(0.0, 0.0, -0.06)).norm() < 3.0 * scatter / 300f64.sqrt());
        // Without noise the point is exact and certain.
        let exact = draw(0, false, 0.0).unwrap();
        assert!(exact.closest_se_m < 1e-9 && (exact.closest_m.z + 0.06).abs() < 1e-9);
        // A sliver at one side leaves the curvature to the noise: far less certain.
        let sliver = draw(0, true, uniform).map_or(f64::INFINITY, |f| f.closest_se_m);
        assert!(sliver > 5.0 * predicted, "{sliver} vs {predicted}");
    }

    #[test]
    fn moments_of_random_points_match_direct_sums() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let pts: Vec<Point3<f64>> = (0..50)
            .map(|_| Point3::new(rng.random(), rng.random(), rng.random()))
            .collect();
        let o = Point3::new(0.5, 0.5, 0.5);
        let m = moments(o, &pts);
        for (n, e) in EXPONENTS.iter().enumerate() {
            let direct: f64 = pts
                .iter()
                .map(|p| {
                    let d = p - o;
                    d.x.powi(e[0].into()) * d.y.powi(e[1].into()) * d.z.powi(e[2].into())
                })
                .sum();
            assert!((direct - m.sums[n]).abs() < 1e-12, "{e:?}");
        }
    }
}
