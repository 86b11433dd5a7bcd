//! Small dense convex QPs, `min 1/2 x^T H x + c^T x  s.t.  A x <= b` with `H` positive
//! definite: the Goldfarb-Idnani dual active-set method (Goldfarb & Idnani 1983, "A
//! numerically stable dual method for solving strictly convex quadratic programs", Math.
//! Prog. 27; the structure of quadprog / QuadProg++), and clarabel (interior point) on the
//! same problem as the reference and the fallback.
//!
//! How it works: with `H = L L^T` the method starts at the unconstrained minimum
//! `x = -H^{-1} c` with no active constraint (dual feasible) and repeatedly takes the most
//! violated row `p`. It moves `x` along `z = J_2 J_2^T n_p` (the step that raises row `p`
//! while keeping the active rows) and the multipliers along `-R^{-1} J_1^T n_p`; a full step
//! makes `p` active, a partial step drops the active row whose multiplier reaches zero first,
//! and when neither is possible (`z = 0` and no multiplier can fall) the rows are infeasible.
//! `J = L^{-T} Q` and the upper triangular `R` with `J^T N = [R; 0]` (`N`: the active
//! normals) are updated by Givens rotations on adding or dropping a row, so an iteration costs
//! `O(n^2 + m n)`, never a refactorisation. Rows are scaled to unit norm first (the primal
//! solution does not change, the tolerances become distances). Every full step raises the
//! dual objective, so the method ends in finitely many steps in exact arithmetic; an
//! iteration cap guards against cycling on rounding. A row that is numerically a combination
//! of the active ones (degenerate) is never divided by: it gets a pure dual step that drops
//! an active row, and when no multiplier can fall either, the rows are reported infeasible.
//!
//! Why hand-written: the controller solves a handful of these per 800 Hz tick with 6-18
//! variables and up to ~40 rows, where an interior-point solve (30-50 KKT factorisations in
//! the bad cases) costs up to a millisecond. The pure-Rust Goldfarb-Idnani crate on
//! crates.io (`quadprog`, 0.0.x) is GPL-2.0, which this BSD-3-Clause crate cannot take;
//! `quadprogpp` binds the C++ QuadProg++ (a C++ toolchain at build time, one release in
//! 2021) and `kquadprog` needs LAPACK through ndarray-linalg. The method is ~200 lines on
//! nalgebra's Cholesky, and clarabel stays as the reference: the property tests below compare
//! the two on random feasible and infeasible problems.
//!
//! No warm start: the method starts cold from the unconstrained minimum every time. In the
//! closed-loop experiments a level's QP takes 4-7 iterations (at most 32 on the benchmark's
//! random states), so seeding it with the previous tick's active set would save little.

use clarabel::algebra::CscMatrix;
use clarabel::solver::{DefaultSettings, DefaultSolver, IPSolver, NonnegativeConeT, SolverStatus};
use nalgebra::{
    DMatrix, DMatrixView, DMatrixViewMut, DVector, DVectorView, DVectorViewMut, Dim, Dyn, Matrix,
    RawStorage, RawStorageMut,
};

/// `min 1/2 x^T h x + c^T x` subject to `a x <= b` (dense).
#[derive(Clone, Debug, PartialEq)]
pub struct DenseQp {
    pub h: DMatrix<f64>,
    pub c: DVector<f64>,
    pub a: DMatrix<f64>,
    pub b: DVector<f64>,
}

impl DenseQp {
    /// The objective at `x`.
    pub fn objective(&self, x: &DVector<f64>) -> f64 {
        0.5 * x.dot(&(&self.h * x)) + self.c.dot(x)
    }

    /// The largest row violation `max(a x - b, 0)` at `x`.
    pub fn max_violation(&self, x: &DVector<f64>) -> f64 {
        (&self.a * x - &self.b)
            .iter()
            .fold(0.0f64, |m, &v| m.max(v))
    }

    fn check(&self) -> Result<(), QpError> {
        let n = self.h.nrows();
        if self.h.ncols() != n
            || self.c.len() != n
            || self.a.ncols() != n
            || self.a.nrows() != self.b.len()
        {
            return Err(QpError::Dimensions);
        }
        let all = self.h.iter().chain(self.c.iter());
        if !all
            .chain(self.a.iter())
            .chain(self.b.iter())
            .all(|v| v.is_finite())
        {
            return Err(QpError::NonFinite);
        }
        Ok(())
    }
}

/// Settings of the active-set method.
#[derive(Clone, Debug, PartialEq)]
pub struct ActiveSetSettings {
    /// Most constraint additions and removals before giving up.
    pub max_iterations: usize,
    /// A (unit-norm) row counts as met when `b - a x >= -tol (1 + |b| + |x|)`.
    pub feasibility_tolerance: f64,
    /// A row is dependent on the active ones when the part of its normal outside their span,
    /// in the metric of `H^{-1}`, is below this fraction of the whole.
    pub dependence_tolerance: f64,
}

impl Default for ActiveSetSettings {
    fn default() -> Self {
        Self {
            max_iterations: 200,
            feasibility_tolerance: 1e-12,
            dependence_tolerance: 1e-10,
        }
    }
}

/// A solution of the active-set method.
#[derive(Clone, Debug, PartialEq)]
pub struct QpSolution {
    pub x: DVector<f64>,
    /// Constraint additions and removals taken.
    pub iterations: usize,
    /// Rows active at the solution (indices into `a`).
    pub active: Vec<usize>,
}

/// Why a QP was not solved.
#[derive(Clone, Debug, thiserror::Error, PartialEq)]
pub enum QpError {
    #[error("QP dimensions are inconsistent")]
    Dimensions,
    #[error("QP has a non-finite entry")]
    NonFinite,
    #[error("QP Hessian is not positive definite")]
    NotPositiveDefinite,
    #[error("QP constraints are infeasible (row {row})")]
    Infeasible { row: usize },
    #[error("QP not solved within {0} iterations")]
    MaxIterations(usize),
    #[error("QP solution violates a row by {0}")]
    Inaccurate(f64),
    #[error("clarabel: {0}")]
    Clarabel(String),
}

/// Reusable buffers of [`solve_active_set_in`], grown to the largest problem seen: a caller
/// that solves problems of the same shapes again (the controller, every tick) allocates
/// nothing after the first solves.
#[derive(Clone, Debug, Default)]
pub struct QpWorkspace {
    a: Vec<f64>,
    b: Vec<f64>,
    usable: Vec<bool>,
    l: Vec<f64>,
    j: Vec<f64>,
    r: Vec<f64>,
    x: Vec<f64>,
    active: Vec<usize>,
    u: Vec<f64>,
    dual: Vec<f64>,
    d: Vec<f64>,
    z: Vec<f64>,
    np: Vec<f64>,
}

impl QpWorkspace {
    /// The solution of the last successful [`solve_active_set_in`] (its first `n` entries).
    pub fn x(&self, n: usize) -> &[f64] {
        &self.x[..n]
    }

    /// Grows every buffer to what [`solve_active_set_in`] needs for up to `m` rows and `n`
    /// unknowns (growing only).
    pub fn reserve(&mut self, m: usize, n: usize) {
        for (buf, len) in [
            (&mut self.a, m * n),
            (&mut self.b, m),
            (&mut self.l, n * n),
            (&mut self.j, n * n),
            (&mut self.r, n * n),
            (&mut self.x, n),
            (&mut self.d, n),
            (&mut self.z, n),
            (&mut self.np, n),
        ] {
            sized(buf, len);
        }
        sized(&mut self.usable, m);
        self.active.reserve(n);
        self.u.reserve(n + 1);
        self.dual.reserve(n);
    }
}

/// The first `len` entries of `buf`, grown (with `T::default()`) when shorter.
pub(crate) fn sized<T: Clone + Default>(buf: &mut Vec<T>, len: usize) -> &mut [T] {
    if buf.len() < len {
        buf.resize(len, T::default());
    }
    &mut buf[..len]
}

/// `m = L L^T` in place: the lower triangle becomes `L`, the upper is zeroed; false when `m`
/// is not (numerically) positive definite. Hand-written: nalgebra's `Cholesky` takes its
/// matrix by value, a copy per solve, and these matrices have at most a few tens of rows.
pub(crate) fn cholesky_in_place(m: &mut DMatrixViewMut<'_, f64>) -> bool {
    let n = m.nrows();
    for j in 0..n {
        let mut diag = m[(j, j)];
        for k in 0..j {
            diag -= m[(j, k)] * m[(j, k)];
        }
        if !(diag > 0.0 && diag.is_finite()) {
            return false;
        }
        let ljj = diag.sqrt();
        m[(j, j)] = ljj;
        for i in j + 1..n {
            let mut v = m[(i, j)];
            for k in 0..j {
                v -= m[(i, k)] * m[(j, k)];
            }
            m[(i, j)] = v / ljj;
        }
        for i in 0..j {
            m[(i, j)] = 0.0;
        }
    }
    true
}

/// `out = a b`, or `a^T b` with `transpose_a`, by plain loops. nalgebra hands products of
/// dynamic matrices beyond a few rows to `matrixmultiply`, which allocates a packing buffer
/// per call; these are at most a few tens of rows.
pub(crate) fn product_into<CB, SA, SB, SO>(
    out: &mut Matrix<f64, Dyn, CB, SO>,
    a: &Matrix<f64, Dyn, Dyn, SA>,
    transpose_a: bool,
    b: &Matrix<f64, Dyn, CB, SB>,
) where
    CB: Dim,
    SA: RawStorage<f64, Dyn, Dyn>,
    SB: RawStorage<f64, Dyn, CB>,
    SO: RawStorageMut<f64, Dyn, CB>,
{
    let (rows, inner) = if transpose_a {
        (a.ncols(), a.nrows())
    } else {
        (a.nrows(), a.ncols())
    };
    let at = |r: usize, k: usize| if transpose_a { a[(k, r)] } else { a[(r, k)] };
    for c in 0..b.ncols() {
        for r in 0..rows {
            out[(r, c)] = (0..inner).map(|k| at(r, k) * b[(k, c)]).sum();
        }
    }
}

/// Solves `L L^T y = x` in place for the factor of [`cholesky_in_place`].
pub(crate) fn cholesky_solve(l: &DMatrixViewMut<'_, f64>, x: &mut DVectorViewMut<'_, f64>) {
    let n = l.nrows();
    for i in 0..n {
        let known: f64 = (0..i).map(|k| l[(i, k)] * x[k]).sum();
        x[i] = (x[i] - known) / l[(i, i)];
    }
    for i in (0..n).rev() {
        let known: f64 = (i + 1..n).map(|k| l[(k, i)] * x[k]).sum();
        x[i] = (x[i] - known) / l[(i, i)];
    }
}

/// Factors of the active set: `J^T N = [R; 0]`, `J J^T = H^{-1}`.
struct Factors<'a> {
    j: DMatrixViewMut<'a, f64>,
    r: DMatrixViewMut<'a, f64>,
    /// Active rows, in the order of `r`'s columns.
    active: &'a mut Vec<usize>,
}

/// The rotation `(c, s)` with `c a + s b = hypot(a, b)` and `-s a + c b = 0`.
fn givens(a: f64, b: f64) -> Option<(f64, f64, f64)> {
    let h = a.hypot(b);
    (h > 0.0 && b != 0.0).then(|| (a / h, b / h, h))
}

/// Rotates columns `i`, `k` of `m`: `(c m_i + s m_k, -s m_i + c m_k)`.
fn rotate_columns(m: &mut DMatrixViewMut<'_, f64>, i: usize, k: usize, c: f64, s: f64) {
    for row in 0..m.nrows() {
        let (u, v) = (m[(row, i)], m[(row, k)]);
        m[(row, i)] = c * u + s * v;
        m[(row, k)] = -s * u + c * v;
    }
}

impl Factors<'_> {
    /// Makes the row with `d = J^T n` active: rotates `d[q..]` into `d[q]` (columns of `J`
    /// beyond the active ones, so `R` is untouched) and appends `d[..=q]` to `R`.
    fn add(&mut self, row: usize, d: &mut DVectorViewMut<'_, f64>) {
        let q = self.active.len();
        for k in (q + 1..d.len()).rev() {
            if let Some((c, s, h)) = givens(d[k - 1], d[k]) {
                d[k - 1] = h;
                d[k] = 0.0;
                rotate_columns(&mut self.j, k - 1, k, c, s);
            }
        }
        for i in 0..=q {
            self.r[(i, q)] = d[i];
        }
        self.active.push(row);
    }

    /// Drops the `l`-th active row: removes column `l` of `R` and restores the triangle
    /// with rotations on rows `l..` of `R` (columns of `J`).
    fn drop(&mut self, l: usize) {
        let q = self.active.len();
        for col in l..q - 1 {
            for i in 0..=col + 1 {
                self.r[(i, col)] = self.r[(i, col + 1)];
            }
        }
        for i in 0..q {
            self.r[(i, q - 1)] = 0.0;
        }
        self.active.remove(l);
        for k in l..q - 1 {
            if let Some((c, s, h)) = givens(self.r[(k, k)], self.r[(k + 1, k)]) {
                self.r[(k, k)] = h;
                self.r[(k + 1, k)] = 0.0;
                for col in k + 1..q - 1 {
                    let (u, v) = (self.r[(k, col)], self.r[(k + 1, col)]);
                    self.r[(k, col)] = c * u + s * v;
                    self.r[(k + 1, col)] = -s * u + c * v;
                }
                rotate_columns(&mut self.j, k, k + 1, c, s);
            }
        }
    }

    /// `R^{-1} d[..q]` by back substitution.
    fn dual_direction(&self, d: &DVectorViewMut<'_, f64>, out: &mut Vec<f64>) {
        let q = self.active.len();
        out.clear();
        out.resize(q, 0.0);
        for i in (0..q).rev() {
            let known: f64 = (i + 1..q).map(|k| self.r[(i, k)] * out[k]).sum();
            out[i] = (d[i] - known) / self.r[(i, i)];
        }
    }
}

/// Solves `qp` by the Goldfarb-Idnani dual active-set method (see the module doc).
pub fn solve_active_set(qp: &DenseQp, settings: &ActiveSetSettings) -> Result<QpSolution, QpError> {
    qp.check()?;
    let n = qp.h.nrows();
    let mut ws = QpWorkspace::default();
    let iterations = solve_active_set_in(
        &qp.h.columns(0, n),
        &qp.c.rows(0, n),
        &qp.a.columns(0, n),
        &qp.b.rows(0, qp.b.len()),
        settings,
        &mut ws,
    )?;
    Ok(QpSolution {
        x: DVector::from_column_slice(ws.x(n)),
        iterations,
        active: ws.active,
    })
}

/// [`solve_active_set`] on views of `min 1/2 x^T h x + c^T x  s.t.  a x <= b`, in the
/// buffers of `ws` (no allocation once they have grown to the problem's size): returns the
/// iterations taken, the solution is [`QpWorkspace::x`].
pub fn solve_active_set_in(
    h: &DMatrixView<'_, f64>,
    c: &DVectorView<'_, f64>,
    a_in: &DMatrixView<'_, f64>,
    b_in: &DVectorView<'_, f64>,
    settings: &ActiveSetSettings,
    ws: &mut QpWorkspace,
) -> Result<usize, QpError> {
    let n = h.nrows();
    let m = a_in.nrows();
    if h.ncols() != n || c.len() != n || a_in.ncols() != n || b_in.len() != m {
        return Err(QpError::Dimensions);
    }
    let all = h.iter().chain(c.iter()).chain(a_in.iter());
    if !all.chain(b_in.iter()).all(|v| v.is_finite()) {
        return Err(QpError::NonFinite);
    }
    let QpWorkspace {
        a,
        b,
        usable,
        l,
        j,
        r,
        x,
        active,
        u,
        dual,
        d,
        z,
        np,
    } = ws;
    // unit-norm rows; an all-zero row is met or infeasible by its sign alone
    let mut a = DMatrixViewMut::from_slice(sized(a, m * n), m, n);
    a.copy_from(a_in);
    let b = sized(b, m);
    let usable = sized(usable, m);
    for i in 0..m {
        b[i] = b_in[i];
        usable[i] = true;
        let norm = a.row(i).norm();
        if norm > 0.0 {
            a.row_mut(i).unscale_mut(norm);
            b[i] /= norm;
        } else if b[i] < -settings.feasibility_tolerance * (1.0 + b[i].abs()) {
            return Err(QpError::Infeasible { row: i });
        } else {
            usable[i] = false;
        }
    }
    let mut l = DMatrixViewMut::from_slice(sized(l, n * n), n, n);
    l.copy_from(h);
    if !cholesky_in_place(&mut l) {
        return Err(QpError::NotPositiveDefinite);
    }
    let mut d = DVectorViewMut::from_slice(sized(d, n), n);
    // J = L^{-T}: column c of L^{-1} by forward substitution is row c of J
    let mut jm = DMatrixViewMut::from_slice(sized(j, n * n), n, n);
    jm.fill(0.0);
    for col in 0..n {
        for i in col..n {
            let known: f64 = (col..i).map(|k| l[(i, k)] * d[k]).sum();
            let identity = if i == col { 1.0 } else { 0.0 };
            d[i] = (identity - known) / l[(i, i)];
            jm[(col, i)] = d[i];
        }
    }
    let mut rm = DMatrixViewMut::from_slice(sized(r, n * n), n, n);
    rm.fill(0.0);
    active.clear();
    active.reserve(n);
    let mut f = Factors {
        j: jm,
        r: rm,
        active,
    };
    let mut x = DVectorViewMut::from_slice(sized(x, n), n);
    x.copy_from(c);
    x.neg_mut();
    cholesky_solve(&l, &mut x);
    // multipliers of the active rows, plus the one of the row being added (last)
    u.clear();
    u.reserve(n + 1);
    dual.clear();
    dual.reserve(n);
    let mut z = DVectorViewMut::from_slice(sized(z, n), n);
    let mut np = DVectorViewMut::from_slice(sized(np, n), n);
    let mut iterations = 0;
    let slack = |x: &DVectorViewMut<'_, f64>, i: usize, a: &DMatrixViewMut<'_, f64>| {
        b[i] - a.row(i).tr_dot(x)
    };
    loop {
        // most violated row
        let xnorm = x.norm();
        let mut pick: Option<(usize, f64)> = None;
        for i in (0..m).filter(|&i| usable[i] && !f.active.contains(&i)) {
            let s = slack(&x, i, &a);
            if s < -settings.feasibility_tolerance * (1.0 + b[i].abs() + xnorm)
                && pick.is_none_or(|(_, best)| s < best)
            {
                pick = Some((i, s));
            }
        }
        let Some((p, mut sp)) = pick else {
            return Ok(iterations);
        };
        // the row's normal for `n^T x >= -b` is `-a_p`
        for k in 0..n {
            np[k] = -a[(p, k)];
        }
        u.push(0.0);
        loop {
            iterations += 1;
            if iterations > settings.max_iterations {
                return Err(QpError::MaxIterations(settings.max_iterations));
            }
            let q = f.active.len();
            product_into(&mut d, &f.j, true, &np);
            z.fill(0.0);
            for k in q..n {
                z.axpy(d[k], &f.j.column(k), 1.0);
            }
            f.dual_direction(&d, dual);
            // partial step: the first active multiplier to reach zero
            let mut partial: Option<(usize, f64)> = None;
            for (k, &rk) in dual.iter().enumerate() {
                if rk > 0.0 {
                    let t = u[k] / rk;
                    if partial.is_none_or(|(_, best)| t < best) {
                        partial = Some((k, t));
                    }
                }
            }
            // full step: row p becomes active, unless its normal is (numerically) in the
            // span of the active ones
            let d2 = d.rows(q, n - q).norm();
            let full = (d2 > settings.dependence_tolerance * d.norm())
                .then(|| (-sp).max(0.0) / (d2 * d2))
                .filter(|t| t.is_finite());
            let step = match (partial, full) {
                (None, None) => return Err(QpError::Infeasible { row: p }),
                (Some((l, t1)), Some(t2)) if t1 < t2 => Step::Partial(l, t1),
                (_, Some(t2)) => Step::Full(t2),
                (Some((l, t1)), None) => Step::Partial(l, t1),
            };
            let t = match step {
                Step::Full(t) | Step::Partial(_, t) => t,
            };
            if full.is_some() {
                x.axpy(t, &z, 1.0);
            }
            for (k, rk) in dual.iter().enumerate() {
                u[k] -= t * rk;
            }
            u[q] += t;
            match step {
                Step::Full(_) => {
                    f.add(p, &mut d);
                    break;
                }
                Step::Partial(l, _) => {
                    f.drop(l);
                    u.remove(l);
                    sp = slack(&x, p, &a);
                }
            }
        }
    }
}

/// One step of the inner loop: make the row active, or drop the `l`-th active row.
enum Step {
    Full(f64),
    Partial(usize, f64),
}

/// Dense matrix to clarabel's CSC (`upper_only`: the upper triangle of a symmetric one).
fn csc_from_dense(m: &DMatrix<f64>, upper_only: bool) -> CscMatrix<f64> {
    let mut colptr = Vec::with_capacity(m.ncols() + 1);
    let mut rowval = Vec::new();
    let mut nzval = Vec::new();
    colptr.push(0);
    for c in 0..m.ncols() {
        let rows = if upper_only { c + 1 } else { m.nrows() };
        for r in 0..rows {
            let v = m[(r, c)];
            if v != 0.0 {
                rowval.push(r);
                nzval.push(v);
            }
        }
        colptr.push(rowval.len());
    }
    CscMatrix::new(m.nrows(), m.ncols(), colptr, rowval, nzval)
}

/// clarabel's settings for [`solve_clarabel`]: quiet, no presolve, `max_iterations`.
pub fn clarabel_settings(max_iterations: u32) -> DefaultSettings<f64> {
    DefaultSettings {
        verbose: false,
        max_iter: max_iterations,
        presolve_enable: false,
        ..DefaultSettings::default()
    }
}

/// Solves `qp` with clarabel (interior point): the reference for [`solve_active_set`] and
/// the fallback where it fails.
pub fn solve_clarabel(
    qp: &DenseQp,
    settings: &DefaultSettings<f64>,
) -> Result<DVector<f64>, QpError> {
    qp.check()?;
    let q: Vec<f64> = qp.c.iter().copied().collect();
    let b: Vec<f64> = qp.b.iter().copied().collect();
    let cones = [NonnegativeConeT(qp.a.nrows())];
    let mut solver = DefaultSolver::new(
        &csc_from_dense(&qp.h, true),
        &q,
        &csc_from_dense(&qp.a, false),
        &b,
        &cones,
        settings.clone(),
    )
    .map_err(|e| QpError::Clarabel(format!("setup: {e:?}")))?;
    solver.solve();
    match solver.solution.status {
        SolverStatus::Solved | SolverStatus::AlmostSolved => {
            Ok(DVector::from_column_slice(&solver.solution.x))
        }
        SolverStatus::PrimalInfeasible | SolverStatus::AlmostPrimalInfeasible => {
            Err(QpError::Clarabel("primal infeasible".into()))
        }
        other => Err(QpError::Clarabel(format!("{other:?}"))),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn qp(h: &[f64], c: &[f64], a: &[f64], b: &[f64]) -> DenseQp {
        let n = c.len();
        DenseQp {
            h: DMatrix::from_row_slice(n, n, h),
            c: DVector::from_column_slice(c),
            a: DMatrix::from_row_slice(b.len(), n, a),
            b: DVector::from_column_slice(b),
        }
    }

    fn active_set(p: &DenseQp) -> Result<QpSolution, QpError> {
        solve_active_set(p, &ActiveSetSettings::default())
    }

    fn clarabel(p: &DenseQp) -> Result<DVector<f64>, QpError> {
        solve_clarabel(p, &clarabel_settings(200))
    }

    #[test]
    fn one_active_row_by_hand() {
        // min 1/2 (x^2 + y^2) + x  s.t.  x + 2 y >= 1: on the line, x + 1 = l, y = 2 l,
        // x + 2 y = 1 gives l = 2/5, (x, y) = (-0.6, 0.8)
        let p = qp(&[1.0, 0.0, 0.0, 1.0], &[1.0, 0.0], &[-1.0, -2.0], &[-1.0]);
        let sol = active_set(&p).unwrap();
        assert!((sol.x[0] + 0.6).abs() < 1e-12 && (sol.x[1] - 0.8).abs() < 1e-12);
        assert_eq!(sol.active, vec![0]);
        assert_eq!(sol.iterations, 1);
    }

    #[test]
    fn unconstrained_minimum_when_rows_are_met() {
        let p = qp(&[2.0, 0.0, 0.0, 4.0], &[-2.0, -4.0], &[1.0, 1.0], &[10.0]);
        let sol = active_set(&p).unwrap();
        assert!((sol.x - DVector::from_vec(vec![1.0, 1.0])).norm() < 1e-12);
        assert!(sol.active.is_empty());
        assert_eq!(sol.iterations, 0);
    }

    #[test]
    fn infeasible_rows_are_reported_by_both() {
        // x <= -1 and x >= 1
        let p = qp(&[1.0], &[0.0], &[1.0, -1.0], &[-1.0, -1.0]);
        assert!(matches!(active_set(&p), Err(QpError::Infeasible { .. })));
        assert!(clarabel(&p).is_err());
        // a zero row with a negative bound: 0 <= -1
        let p = qp(&[1.0], &[0.0], &[0.0], &[-1.0]);
        assert_eq!(active_set(&p), Err(QpError::Infeasible { row: 0 }));
    }

    #[test]
    fn dependent_and_repeated_rows() {
        // the optimum (1, 1) sits on four rows through one point in the plane, two of them
        // copies: more active candidates than variables, all but two dependent
        let p = qp(
            &[1.0, 0.0, 0.0, 1.0],
            &[-3.0, -3.0],
            &[1.0, 0.0, 0.0, 1.0, 1.0, 0.0, 1.0, 1.0, 2.0, 2.0],
            &[1.0, 1.0, 1.0, 2.0, 4.0],
        );
        let sol = active_set(&p).unwrap();
        assert!(
            (&sol.x - DVector::from_vec(vec![1.0, 1.0])).norm() < 1e-10,
            "{}",
            sol.x
        );
        assert!(sol.active.len() <= 2);
        let reference = clarabel(&p).unwrap();
        assert!((p.objective(&sol.x) - p.objective(&reference)).abs() < 1e-6);
    }

    #[test]
    fn bad_problems_are_errors_not_panics() {
        let p = qp(&[1.0, 2.0, 2.0, 1.0], &[0.0, 0.0], &[], &[]);
        assert_eq!(active_set(&p), Err(QpError::NotPositiveDefinite));
        let p = qp(&[1.0], &[f64::NAN], &[1.0], &[0.0]);
        assert_eq!(active_set(&p), Err(QpError::NonFinite));
        let mut p = qp(&[1.0], &[0.0], &[1.0], &[0.0]);
        p.b = DVector::zeros(2);
        assert_eq!(active_set(&p), Err(QpError::Dimensions));
        // a violated row and no iterations allowed
        let p = qp(&[1.0], &[0.0], &[-1.0], &[-1.0]);
        let none = ActiveSetSettings {
            max_iterations: 0,
            ..ActiveSetSettings::default()
        };
        assert_eq!(solve_active_set(&p, &none), Err(QpError::MaxIterations(0)));
    }

    /// A random positive definite Hessian `B^T B + mu I`, a random linear term and rows
    /// met by a random point `x0` (so the problem is feasible); `tight` rows pass through
    /// `x0`, which makes degenerate vertices common.
    fn feasible_qp() -> impl Strategy<Value = DenseQp> {
        (1usize..=8, 0usize..=24).prop_flat_map(|(n, m)| {
            (
                proptest::collection::vec(-2.0..2.0f64, n * n),
                proptest::collection::vec(-3.0..3.0f64, n),
                proptest::collection::vec(-2.0..2.0f64, m * n),
                proptest::collection::vec(-1.0..1.0f64, n),
                proptest::collection::vec(prop_oneof![Just(0.0), 0.0..2.0f64], m),
                1e-3..1.0f64,
            )
                .prop_map(move |(bm, c, a, x0, gap, mu)| {
                    let bm = DMatrix::from_row_slice(n, n, &bm);
                    let h = bm.transpose() * &bm + DMatrix::identity(n, n) * mu;
                    let a = DMatrix::from_row_slice(m, n, &a);
                    let b = &a * DVector::from_vec(x0) + DVector::from_vec(gap);
                    DenseQp {
                        h,
                        c: DVector::from_vec(c),
                        a,
                        b,
                    }
                })
        })
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(256))]

        /// On random feasible problems the active-set solution is feasible and its objective
        /// is clarabel's (interior point, the reference), within clarabel's own accuracy.
        #[test]
        fn matches_clarabel_on_feasible_problems(p in feasible_qp()) {
            let sol = active_set(&p).unwrap();
            let scale = 1.0 + sol.x.norm() + p.b.amax();
            prop_assert!(p.max_violation(&sol.x) <= 1e-9 * scale, "violation {}", p.max_violation(&sol.x));
            // Clarabel may stop at its iteration cap (the saved regression case): there is then
            // no reference optimum to compare with.
            if let Ok(reference) = clarabel(&p) {
                let (f, f_ref) = (p.objective(&sol.x), p.objective(&reference));
                prop_assert!(f <= f_ref + 1e-6 * (1.0 + f_ref.abs()), "objective {f} vs clarabel {f_ref}");
                prop_assert!(f >= f_ref - 1e-6 * (1.0 + f_ref.abs()) - 1e-6 * p.max_violation(&reference),
                    "objective {f} below clarabel's {f_ref}");
            }
        }

        /// The hierarchy's level problems: a nearly singular block (`1e-9 I` on the step, the
        /// Tikhonov term of a level with no equalities) beside unit slack weights, rows on
        /// the step only and rows with a slack each.
        #[test]
        fn matches_clarabel_on_hierarchy_shaped_problems(
            nz in 1usize..=6,
            rows in proptest::collection::vec((proptest::collection::vec(-2.0..2.0f64, 6), -1.0..1.0f64), 1..12),
            own in 0usize..4,
        ) {
            let own = own.min(rows.len());
            let n = nz + own;
            let mut h = DMatrix::identity(n, n);
            h.view_mut((0, 0), (nz, nz)).fill_with_identity();
            h.view_mut((0, 0), (nz, nz)).scale_mut(1e-9);
            let mut a = DMatrix::zeros(rows.len(), n);
            let mut b = DVector::zeros(rows.len());
            for (i, (r, bi)) in rows.iter().enumerate() {
                for k in 0..nz {
                    a[(i, k)] = r[k];
                }
                if i < own {
                    a[(i, nz + i)] = -1.0;
                }
                // step rows are met at z = 0 (higher levels always are)
                b[i] = if i < own { *bi } else { bi.abs() };
            }
            let p = DenseQp { h, c: DVector::zeros(n), a, b };
            let sol = active_set(&p).unwrap();
            prop_assert!(p.max_violation(&sol.x) <= 1e-9, "violation {}", p.max_violation(&sol.x));
            // The 1e-9 block can stall the reference itself (clarabel at its iteration cap on
            // the saved regression case); there is then no optimum to compare with.
            if let Ok(reference) = clarabel(&p) {
                let (f, f_ref) = (p.objective(&sol.x), p.objective(&reference));
                prop_assert!((f - f_ref).abs() <= 1e-6 * (1.0 + f_ref.abs()), "objective {f} vs clarabel {f_ref}");
            }
        }

        /// A pair of contradicting rows hidden among random feasible ones: both solvers
        /// report the problem infeasible.
        #[test]
        fn infeasible_problems_are_flagged_by_both(p in feasible_qp(), row in proptest::collection::vec(-2.0..2.0f64, 8), gap in 0.01..1.0f64) {
            let n = p.h.nrows();
            let r = DVector::from_column_slice(&row[..n]);
            prop_assume!(r.norm() > 0.1);
            let m = p.a.nrows();
            let mut a = p.a.clone().insert_rows(m, 2, 0.0);
            a.row_mut(m).copy_from(&r.transpose());
            a.row_mut(m + 1).copy_from(&(-r.transpose()));
            // r x <= 0 and r x >= gap
            let b = p.b.clone().insert_rows(m, 2, 0.0);
            let mut b = b;
            b[m + 1] = -gap;
            let bad = DenseQp { a, b, ..p };
            prop_assert!(matches!(active_set(&bad), Err(QpError::Infeasible { .. })), "{:?}", active_set(&bad));
            prop_assert!(clarabel(&bad).is_err());
        }
    }
}
