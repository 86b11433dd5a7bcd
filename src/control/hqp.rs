//! Hierarchical quadratic programming: prioritised tasks with equalities and inequalities
//! solved as a cascade of QPs, each in the null space of the equalities above and inside the
//! (relaxed) inequalities above (Kanoun 2011, de Lasa 2010, Hutter 2014, Bellicoso 2016).
//!
//! Level `p` has equalities `A_p x = b_p` (least squares) and inequalities `D_p x <= f_p`.
//! With `x = x_{p-1} + Z_{p-1} z` and slacks `v`:
//!
//! ```text
//! min  1/2 |A_p (x_{p-1} + Z z) - b_p|^2 + 1/2 |v|^2 + 1/2 eps |z|^2
//! s.t. D_p (x_{p-1} + Z z) - v <= f_p
//!      D_j (x_{p-1} + Z z) <= f_j + v_j* + tol        for every higher level j
//! ```
//!
//! then `x_p = x_{p-1} + Z z*`, `v_p* = max(D_p x_p - f_p, 0)` and
//! `Z_p = Z_{p-1} null(A_p Z_{p-1})`. Because every later step moves inside `Z_p` and keeps
//! the higher inequalities, a lower level can never undo a higher one.
//!
//! Speed: a level is handed to a QP solver only when it has to be. When the unconstrained
//! least-squares step (a Cholesky solve) already meets every inequality, it is the exact
//! optimum of the level's QP (objective and slack both at their minima), so no QP is solved;
//! this is the common case of a controller far from its limits. Otherwise the level's QP
//! (all its rows, a slack per own row) goes to the Goldfarb-Idnani active-set method of
//! [`super::qp`], which on these small dense problems (6 + k variables, tens of rows) takes
//! a few microseconds where clarabel's interior point took 30-50 iterations in its worst
//! cases. Its solution is checked against every row; if the method fails (iteration cap,
//! rounding) or the check does, the level falls back to clarabel on a working set of rows
//! (see [`HierarchicalSolver::solve_qp_working_set`]) and the report says so
//! ([`LevelMethod::QpFallback`] with the active-set failure), so a failure of the new solver
//! is never less safe than clarabel alone. The null space is the eigenspace of
//! `(A Z)^T (A Z)` with eigenvalues below a relative tolerance; when no freedom is left, the
//! remaining levels only report slacks.

use super::qp::{self, ActiveSetSettings, DenseQp, QpError, QpWorkspace};
use arrayvec::ArrayVec;
use clarabel::solver::DefaultSettings;
use nalgebra::{DMatrix, DMatrixView, DMatrixViewMut, DVector, DVectorView, DVectorViewMut};

/// One priority level: equalities `a x = b` and inequalities `d x <= f`.
#[derive(Clone, Debug)]
pub struct Task {
    pub name: &'static str,
    pub a: DMatrix<f64>,
    pub b: DVector<f64>,
    pub d: DMatrix<f64>,
    pub f: DVector<f64>,
}

impl Task {
    /// A level with no rows (to be filled with [`Task::equalities`] / [`Task::inequalities`]).
    pub fn new(name: &'static str, n: usize) -> Self {
        Self {
            name,
            a: DMatrix::zeros(0, n),
            b: DVector::zeros(0),
            d: DMatrix::zeros(0, n),
            f: DVector::zeros(0),
        }
    }

    pub fn equalities(mut self, a: DMatrix<f64>, b: DVector<f64>) -> Self {
        self.a = a;
        self.b = b;
        self
    }

    pub fn inequalities(mut self, d: DMatrix<f64>, f: DVector<f64>) -> Self {
        self.d = d;
        self.f = f;
        self
    }
}

/// Numerical settings of the cascade.
#[derive(Clone, Debug, PartialEq)]
pub struct HqpSettings {
    /// Tikhonov weight `eps` on the step `z` (keeps each level's Hessian positive definite).
    pub regularization: f64,
    /// Relative eigenvalue threshold below which a direction counts as null.
    pub null_space_tolerance: f64,
    /// Amount by which higher inequalities are loosened for the levels below, so that solver
    /// rounding cannot turn an active constraint infeasible.
    pub feasibility_tolerance: f64,
    /// Interior-point iteration limit per QP (the clarabel fallback).
    pub max_iterations: u32,
    /// The active-set method that solves a level's QP first.
    pub active_set: ActiveSetSettings,
}

impl Default for HqpSettings {
    fn default() -> Self {
        Self {
            regularization: 1e-9,
            null_space_tolerance: 1e-10,
            feasibility_tolerance: 1e-7,
            max_iterations: 50,
            active_set: ActiveSetSettings::default(),
        }
    }
}

/// How a level was solved.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LevelMethod {
    /// The unconstrained least-squares step met every inequality.
    LeastSquares,
    /// The level's QP was solved by the active-set method.
    Qp,
    /// The active-set method failed (see [`LevelReport::qp_failure`]); clarabel solved it.
    QpFallback,
    /// No freedom was left; the level was only evaluated.
    NoFreedom,
}

/// Most levels a hierarchy may have, and most inequality rows one level may have (the
/// reports are fixed-size, so a solve allocates nothing).
pub const MAX_LEVELS: usize = 8;
pub const MAX_LEVEL_ROWS: usize = 48;

/// Outcome of one level.
#[derive(Clone, Debug, PartialEq)]
pub struct LevelReport {
    pub name: &'static str,
    pub method: LevelMethod,
    /// `|A_p x_p - b_p|` after the level.
    pub equality_residual: f64,
    /// Optimal slacks `v_p*` of the level's inequalities (zero when all are met).
    pub slacks: ArrayVec<f64, MAX_LEVEL_ROWS>,
    /// Dimension of the null space left for the levels below.
    pub freedom_left: usize,
    /// Iterations (row additions and removals) of the active-set method, 0 without a QP.
    pub qp_iterations: usize,
    /// Why the active-set method did not serve a [`LevelMethod::QpFallback`] level.
    pub qp_failure: Option<QpError>,
}

/// The solution of the whole hierarchy.
#[derive(Clone, Debug, PartialEq)]
pub struct HqpSolution {
    pub x: DVector<f64>,
    pub levels: ArrayVec<LevelReport, MAX_LEVELS>,
}

/// Why a hierarchy could not be solved.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum HqpError {
    #[error("task `{task}` has inconsistent dimensions")]
    Dimensions { task: &'static str },
    #[error("task `{task}` has a non-finite entry")]
    NonFinite { task: &'static str },
    #[error("QP of task `{task}` failed: {status}")]
    Solver { task: &'static str, status: String },
    #[error(
        "hierarchy too large: at most {MAX_LEVELS} levels of at most {MAX_LEVEL_ROWS} inequalities (task `{task}`)"
    )]
    TooLarge { task: &'static str },
}

/// Solves task hierarchies over `n` variables; holds the solver settings between calls.
#[derive(Clone, Debug)]
pub struct HierarchicalSolver {
    n: usize,
    settings: HqpSettings,
    qp_settings: DefaultSettings<f64>,
}

/// Reusable buffers of [`HierarchicalSolver::solve_in`] and its solution, grown to the
/// largest hierarchy seen: solving hierarchies of the same shapes again (the controller,
/// every tick) allocates nothing. Only the clarabel fallback allocates.
#[derive(Clone, Debug)]
pub struct HqpWorkspace {
    solution: HqpSolution,
    basis: Vec<f64>,
    basis_next: Vec<f64>,
    dh: Vec<f64>,
    fh: Vec<f64>,
    az: Vec<f64>,
    r: Vec<f64>,
    hess: Vec<f64>,
    chol: Vec<f64>,
    grad: Vec<f64>,
    z_ls: Vec<f64>,
    dz: Vec<f64>,
    s: Vec<f64>,
    dhz: Vec<f64>,
    sh: Vec<f64>,
    qp_h: Vec<f64>,
    qp_c: Vec<f64>,
    qp_a: Vec<f64>,
    qp_b: Vec<f64>,
    gram: Vec<f64>,
    eigenvectors: Vec<f64>,
    qp: QpWorkspace,
}

impl Default for HqpWorkspace {
    fn default() -> Self {
        Self {
            solution: HqpSolution {
                x: DVector::zeros(0),
                levels: ArrayVec::new(),
            },
            basis: Vec::new(),
            basis_next: Vec::new(),
            dh: Vec::new(),
            fh: Vec::new(),
            az: Vec::new(),
            r: Vec::new(),
            hess: Vec::new(),
            chol: Vec::new(),
            grad: Vec::new(),
            z_ls: Vec::new(),
            dz: Vec::new(),
            s: Vec::new(),
            dhz: Vec::new(),
            sh: Vec::new(),
            qp_h: Vec::new(),
            qp_c: Vec::new(),
            qp_a: Vec::new(),
            qp_b: Vec::new(),
            gram: Vec::new(),
            eigenvectors: Vec::new(),
            qp: QpWorkspace::default(),
        }
    }
}

impl HqpWorkspace {
    /// Grows every buffer to what [`HierarchicalSolver::solve_in`] needs for hierarchies of
    /// `n` unknowns shaped like `tasks` (each level's rows at most as many as there), so that
    /// already the first solve allocates nothing (the clarabel fallback aside). Growing
    /// only: calls for several shapes keep the largest.
    pub fn reserve(&mut self, n: usize, tasks: &[Task]) {
        let total: usize = tasks.iter().map(|t| t.d.nrows()).sum();
        let me = tasks.iter().map(|t| t.a.nrows()).max().unwrap_or(0);
        let k = tasks.iter().map(|t| t.d.nrows()).max().unwrap_or(0);
        // a level's QP: its `nz + k` unknowns (nz <= n), its own and the higher rows
        let (nv, rows) = (n + k, k + total);
        for (buf, len) in [
            (&mut self.basis, n * n),
            (&mut self.basis_next, n * n),
            (&mut self.dh, total * n),
            (&mut self.fh, total),
            (&mut self.az, me * n),
            (&mut self.r, me),
            (&mut self.hess, n * n),
            (&mut self.chol, n * n),
            (&mut self.grad, n),
            (&mut self.z_ls, n),
            (&mut self.dz, k * n),
            (&mut self.s, k),
            (&mut self.dhz, total * n),
            (&mut self.sh, total),
            (&mut self.qp_h, nv * nv),
            (&mut self.qp_c, nv),
            (&mut self.qp_a, rows * nv),
            (&mut self.qp_b, rows),
            (&mut self.gram, n * n),
            (&mut self.eigenvectors, n * n),
        ] {
            qp::sized(buf, len);
        }
        if self.solution.x.len() != n {
            self.solution.x = DVector::zeros(n);
        }
        self.qp.reserve(rows, nv);
    }
}

/// A `rows x cols` matrix view on the first entries of `buf` (grown when short).
fn view_mut(buf: &mut Vec<f64>, rows: usize, cols: usize) -> DMatrixViewMut<'_, f64> {
    DMatrixViewMut::from_slice(qp::sized(buf, rows * cols), rows, cols)
}

/// A vector view of length `len` on the first entries of `buf` (grown when short).
fn vector_mut(buf: &mut Vec<f64>, len: usize) -> DVectorViewMut<'_, f64> {
    DVectorViewMut::from_slice(qp::sized(buf, len), len)
}

/// Eigen-decomposition of the symmetric `a` by cyclic Jacobi rotations: `a` ends diagonal
/// (the eigenvalues), the columns of `v` are the eigenvectors. Hand-written because
/// nalgebra's `SymmetricEigen` allocates its results; these matrices have at most a dozen
/// rows, where Jacobi is accurate to rounding in a few sweeps.
fn symmetric_eigen_in_place(a: &mut DMatrixViewMut<'_, f64>, v: &mut DMatrixViewMut<'_, f64>) {
    let n = a.nrows();
    v.fill_with_identity();
    for _sweep in 0..64 {
        let off: f64 = (0..n)
            .flat_map(|p| (p + 1..n).map(move |q| (p, q)))
            .map(|(p, q)| a[(p, q)] * a[(p, q)])
            .sum();
        let diag: f64 = (0..n).map(|i| a[(i, i)] * a[(i, i)]).sum();
        // converged (or not a number: the sweeps would not help)
        if off.is_nan() || off <= f64::EPSILON * f64::EPSILON * (diag + off) {
            return;
        }
        for p in 0..n {
            for q in p + 1..n {
                let apq = a[(p, q)];
                if apq == 0.0 {
                    continue;
                }
                // the rotation that zeroes a[p][q] (Numerical Recipes, `jacobi`)
                let theta = (a[(q, q)] - a[(p, p)]) / (2.0 * apq);
                let t = theta.signum() / (theta.abs() + theta.hypot(1.0));
                let c = 1.0 / t.hypot(1.0);
                let s = t * c;
                for k in 0..n {
                    let (akp, akq) = (a[(k, p)], a[(k, q)]);
                    a[(k, p)] = c * akp - s * akq;
                    a[(k, q)] = s * akp + c * akq;
                }
                for k in 0..n {
                    let (apk, aqk) = (a[(p, k)], a[(q, k)]);
                    a[(p, k)] = c * apk - s * aqk;
                    a[(q, k)] = s * apk + c * aqk;
                }
                for k in 0..n {
                    let (vkp, vkq) = (v[(k, p)], v[(k, q)]);
                    v[(k, p)] = c * vkp - s * vkq;
                    v[(k, q)] = s * vkp + c * vkq;
                }
            }
        }
    }
}

impl HierarchicalSolver {
    pub fn new(n: usize, settings: HqpSettings) -> Self {
        let qp_settings = qp::clarabel_settings(settings.max_iterations);
        Self {
            n,
            settings,
            qp_settings,
        }
    }

    /// Solves the hierarchy `tasks` (highest priority first).
    pub fn solve(&self, tasks: &[Task]) -> Result<HqpSolution, HqpError> {
        let mut workspace = HqpWorkspace::default();
        self.solve_in(tasks, &mut workspace).cloned()
    }

    /// [`HierarchicalSolver::solve`] in the buffers of `ws`: no allocation once they have
    /// grown to the hierarchy's shapes (unless a level needs the clarabel fallback).
    pub fn solve_in<'w>(
        &self,
        tasks: &[Task],
        ws: &'w mut HqpWorkspace,
    ) -> Result<&'w HqpSolution, HqpError> {
        let n = self.n;
        if let Some(t) = tasks.get(MAX_LEVELS) {
            return Err(HqpError::TooLarge { task: t.name });
        }
        for t in tasks {
            if t.a.ncols() != n
                || t.d.ncols() != n
                || t.a.nrows() != t.b.len()
                || t.d.nrows() != t.f.len()
            {
                return Err(HqpError::Dimensions { task: t.name });
            }
            if t.d.nrows() > MAX_LEVEL_ROWS {
                return Err(HqpError::TooLarge { task: t.name });
            }
            let finite =
                t.a.iter()
                    .chain(t.b.iter())
                    .chain(t.d.iter())
                    .chain(t.f.iter());
            if finite.copied().any(|v| !v.is_finite()) {
                return Err(HqpError::NonFinite { task: t.name });
            }
        }
        let tol = self.settings.feasibility_tolerance;
        let HqpWorkspace {
            solution,
            basis,
            basis_next,
            dh,
            fh,
            az,
            r,
            hess,
            chol,
            grad,
            z_ls,
            dz,
            s,
            dhz,
            sh,
            qp_h,
            qp_c,
            qp_a,
            qp_b,
            gram,
            eigenvectors,
            qp,
        } = ws;
        if solution.x.len() != n {
            solution.x = DVector::zeros(n);
        }
        let x = &mut solution.x;
        x.fill(0.0);
        solution.levels.clear();
        view_mut(basis, n, n).fill_with_identity();
        let mut nz = n;
        // accumulated higher inequalities with their relaxed right-hand sides
        let total_rows: usize = tasks.iter().map(|t| t.d.nrows()).sum();
        qp::sized(dh, total_rows * n);
        qp::sized(fh, total_rows);
        let mut rows_h = 0;
        for (p, t) in tasks.iter().enumerate() {
            let k = t.d.nrows();
            let me = t.a.nrows();
            let (mut qp_iterations, mut qp_failure) = (0, None);
            let method = if nz == 0 {
                LevelMethod::NoFreedom
            } else {
                let bm = DMatrixView::from_slice(&basis[..n * nz], n, nz);
                let mut azm = view_mut(az, me, nz);
                qp::product_into(&mut azm, &t.a, false, &bm);
                let mut rv = vector_mut(r, me);
                rv.copy_from(&t.b);
                rv.gemv(-1.0, &t.a, &*x, 1.0);
                let mut hm = view_mut(hess, nz, nz);
                qp::product_into(&mut hm, &azm, true, &azm);
                for i in 0..nz {
                    hm[(i, i)] += self.settings.regularization;
                }
                let mut gv = vector_mut(grad, nz);
                qp::product_into(&mut gv, &azm, true, &rv);
                let mut zv = vector_mut(z_ls, nz);
                zv.fill(0.0);
                if me > 0 {
                    let mut cm = view_mut(chol, nz, nz);
                    cm.copy_from(&hm);
                    if qp::cholesky_in_place(&mut cm) {
                        zv.copy_from(&gv);
                        qp::cholesky_solve(&cm, &mut zv);
                    }
                }
                let mut dzm = view_mut(dz, k, nz);
                qp::product_into(&mut dzm, &t.d, false, &bm);
                let mut sv = vector_mut(s, k);
                sv.copy_from(&t.f);
                sv.gemv(-1.0, &t.d, &*x, 1.0);
                let dh_all = DMatrixView::from_slice(&dh[..total_rows * n], total_rows, n);
                let dhv = dh_all.rows(0, rows_h);
                let mut dhzm = view_mut(dhz, rows_h, nz);
                qp::product_into(&mut dhzm, &dhv, false, &bm);
                let mut shv = vector_mut(sh, rows_h);
                shv.copy_from(&DVectorView::from_slice(&fh[..rows_h], rows_h));
                shv.gemv(-1.0, &dhv, &*x, 1.0);
                let meets = |dm: &DMatrixViewMut<'_, f64>, rhs: &DVectorViewMut<'_, f64>| {
                    (0..dm.nrows()).all(|i| dm.row(i).tr_dot(&zv) - rhs[i] <= tol)
                };
                if meets(&dzm, &sv) && meets(&dhzm, &shv) {
                    x.gemv(1.0, &bm, &zv, 1.0);
                    LevelMethod::LeastSquares
                } else {
                    let level = Level {
                        hess: hm.as_view(),
                        grad: gv.as_view(),
                        dz: dzm.as_view(),
                        s: sv.as_view(),
                        dhz: dhzm.as_view(),
                        sh: shv.as_view(),
                    };
                    let (nv, rows) = (nz + k, k + rows_h);
                    let mut qh = view_mut(qp_h, nv, nv);
                    let mut qc = vector_mut(qp_c, nv);
                    let mut qa = view_mut(qp_a, rows, nv);
                    let mut qb = vector_mut(qp_b, rows);
                    level.fill(&mut qh, &mut qc, &mut qa, &mut qb);
                    let (qh, qc): (DMatrixView<'_, f64>, DVectorView<'_, f64>) =
                        (qh.as_view(), qc.as_view());
                    let (qa, qb): (DMatrixView<'_, f64>, DVectorView<'_, f64>) =
                        (qa.as_view(), qb.as_view());
                    let solved =
                        qp::solve_active_set_in(&qh, &qc, &qa, &qb, &self.settings.active_set, qp);
                    let violation = |xq: &[f64]| {
                        (0..rows).fold(0.0f64, |m, i| {
                            let v: f64 = (0..nv).map(|c| qa[(i, c)] * xq[c]).sum();
                            m.max(v - qb[i])
                        })
                    };
                    match solved {
                        Ok(iterations) if violation(qp.x(nv)) <= tol => {
                            let zq = DVectorView::from_slice(&qp.x(nv)[..nz], nz);
                            x.gemv(1.0, &bm, &zq, 1.0);
                            qp_iterations = iterations;
                            LevelMethod::Qp
                        }
                        failed => {
                            qp_failure = Some(match failed {
                                Ok(_) => QpError::Inaccurate(violation(qp.x(nv))),
                                Err(e) => e,
                            });
                            let z = self.solve_qp_working_set(t.name, &level, &zv)?;
                            x.gemv(1.0, &bm, &z, 1.0);
                            LevelMethod::QpFallback
                        }
                    }
                }
            };
            // optimal slacks from the final x of this level
            let mut slacks = ArrayVec::new();
            let mut dh_all = DMatrixViewMut::from_slice(&mut dh[..total_rows * n], total_rows, n);
            for i in 0..k {
                let v = (t.d.row(i).tr_dot(&*x) - t.f[i]).max(0.0);
                slacks.push(v);
                dh_all.row_mut(rows_h + i).copy_from(&t.d.row(i));
                fh[rows_h + i] = t.f[i] + v + tol;
            }
            rows_h += k;
            let last = p + 1 == tasks.len();
            if me > 0 && !last && nz > 0 {
                // basis * null(A basis), via the eigen-decomposition of (A basis)^T (A basis)
                let azm = DMatrixView::from_slice(&az[..me * nz], me, nz);
                let mut gm = view_mut(gram, nz, nz);
                qp::product_into(&mut gm, &azm, true, &azm);
                let mut vm = view_mut(eigenvectors, nz, nz);
                symmetric_eigen_in_place(&mut gm, &mut vm);
                let scale = (0..nz).map(|i| gm[(i, i)]).fold(1.0f64, f64::max);
                let bound = self.settings.null_space_tolerance * scale;
                let bm = DMatrixView::from_slice(&basis[..n * nz], n, nz);
                let mut next = view_mut(basis_next, n, nz);
                let mut kept = 0;
                for i in (0..nz).filter(|&i| gm[(i, i)] <= bound) {
                    next.column_mut(kept).gemv(1.0, &bm, &vm.column(i), 0.0);
                    kept += 1;
                }
                // the kept columns, packed at the front, are the new basis
                std::mem::swap(basis, basis_next);
                nz = kept;
            }
            let residual = (0..me)
                .map(|i| (t.a.row(i).tr_dot(&*x) - t.b[i]).powi(2))
                .sum::<f64>()
                .sqrt();
            solution.levels.push(LevelReport {
                name: t.name,
                method,
                equality_residual: residual,
                slacks,
                freedom_left: nz,
                qp_iterations,
                qp_failure,
            });
        }
        Ok(solution)
    }

    /// One level's QP, solved on a working set of its rows: first the rows (own and higher)
    /// that the least-squares step `z_ls` violates, then, while the QP's solution violates a
    /// row left out, with those rows added. Leaving out rows relaxes the QP, so a solution of
    /// the relaxed QP that meets every row left out (an own row with a zero slack) is the
    /// optimum of the full QP: the result is exact, and the QP handed to clarabel usually has
    /// a handful of rows instead of all 20-30 of the hierarchy (its interior-point iterations
    /// factorise a KKT system of `nz + 2 * rows` unknowns, which dominates the tick). Each
    /// round adds at least one row, so the loop ends after at most `rows` rounds.
    fn solve_qp_working_set(
        &self,
        name: &'static str,
        level: &Level<'_>,
        z_ls: &DVectorViewMut<'_, f64>,
    ) -> Result<DVector<f64>, HqpError> {
        let tol = self.settings.feasibility_tolerance;
        let Level { dz, s, dhz, sh, .. } = *level;
        let (k, kh) = (dz.nrows(), dhz.nrows());
        let violated = |z: &DVector<f64>, own: &[bool], high: &[bool]| {
            let own_v: Vec<usize> = (0..k)
                .filter(|&i| !own[i] && dz.row(i).tr_dot(z) - s[i] > tol)
                .collect();
            let high_v: Vec<usize> = (0..kh)
                .filter(|&i| !high[i] && dhz.row(i).tr_dot(z) - sh[i] > tol)
                .collect();
            (own_v, high_v)
        };
        let mut own = vec![false; k];
        let mut high = vec![false; kh];
        let (mut add_own, mut add_high) = violated(&z_ls.clone_owned(), &own, &high);
        loop {
            add_own.iter().for_each(|&i| own[i] = true);
            add_high.iter().for_each(|&i| high[i] = true);
            let pick = |m: &DMatrixView<'_, f64>, v: &DVectorView<'_, f64>, sel: &[bool]| {
                let idx: Vec<usize> = (0..sel.len()).filter(|&i| sel[i]).collect();
                (m.select_rows(idx.iter()), v.select_rows(idx.iter()))
            };
            let (dzw, sw) = pick(&dz, &s, &own);
            let (dhw, shw) = pick(&dhz, &sh, &high);
            let working = Level {
                dz: dzw.as_view(),
                s: sw.as_view(),
                dhz: dhw.as_view(),
                sh: shw.as_view(),
                ..*level
            };
            let z = qp::solve_clarabel(&working.qp(), &self.qp_settings)
                .map(|x| x.rows(0, level.hess.nrows()).into_owned())
                .map_err(|e| HqpError::Solver {
                    task: name,
                    status: e.to_string(),
                })?;
            (add_own, add_high) = violated(&z, &own, &high);
            if add_own.is_empty() && add_high.is_empty() {
                return Ok(z);
            }
        }
    }
}

/// One level's problem in the step `z` (module doc): Hessian and gradient of the equality
/// objective, own rows `dz z <= s` and the higher rows `dhz z <= sh`.
#[derive(Clone, Copy)]
struct Level<'a> {
    hess: DMatrixView<'a, f64>,
    grad: DVectorView<'a, f64>,
    dz: DMatrixView<'a, f64>,
    s: DVectorView<'a, f64>,
    dhz: DMatrixView<'a, f64>,
    sh: DVectorView<'a, f64>,
}

impl Level<'_> {
    /// The level's QP over `[z; v]`: `min 1/2 z^T hess z - grad^T z + 1/2 |v|^2` subject to
    /// `dz z - v <= s` (one slack per own row) and `dhz z <= sh`.
    fn qp(&self) -> DenseQp {
        let nz = self.hess.nrows();
        let (k, kh) = (self.dz.nrows(), self.dhz.nrows());
        let (nv, rows) = (nz + k, k + kh);
        let mut qp = DenseQp {
            h: DMatrix::zeros(nv, nv),
            c: DVector::zeros(nv),
            a: DMatrix::zeros(rows, nv),
            b: DVector::zeros(rows),
        };
        self.fill(
            &mut qp.h.view_mut((0, 0), (nv, nv)),
            &mut qp.c.rows_mut(0, nv),
            &mut qp.a.view_mut((0, 0), (rows, nv)),
            &mut qp.b.rows_mut(0, rows),
        );
        qp
    }

    /// Writes [`Level::qp`] into views of its shape (`nz + k` variables, `k + kh` rows).
    fn fill(
        &self,
        h: &mut DMatrixViewMut<'_, f64>,
        c: &mut DVectorViewMut<'_, f64>,
        a: &mut DMatrixViewMut<'_, f64>,
        b: &mut DVectorViewMut<'_, f64>,
    ) {
        let nz = self.hess.nrows();
        let (k, kh) = (self.dz.nrows(), self.dhz.nrows());
        h.fill(0.0);
        h.view_mut((0, 0), (nz, nz)).copy_from(&self.hess);
        for i in 0..k {
            h[(nz + i, nz + i)] = 1.0;
        }
        c.fill(0.0);
        for i in 0..nz {
            c[i] = -self.grad[i];
        }
        a.fill(0.0);
        a.view_mut((0, 0), (k, nz)).copy_from(&self.dz);
        for i in 0..k {
            a[(i, nz + i)] = -1.0;
            b[i] = self.s[i];
        }
        a.view_mut((k, 0), (kh, nz)).copy_from(&self.dhz);
        for i in 0..kh {
            b[k + i] = self.sh[i];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn solver(n: usize) -> HierarchicalSolver {
        HierarchicalSolver::new(n, HqpSettings::default())
    }

    #[test]
    fn equality_priority_and_null_space() {
        // level 1: x0 + x1 = 1; level 2: x0 = 5, x1 = 5 (conflicts); level 3: x2 = 3
        let t1 = Task::new("sum", 3).equalities(
            DMatrix::from_row_slice(1, 3, &[1.0, 1.0, 0.0]),
            DVector::from_vec(vec![1.0]),
        );
        let t2 = Task::new("fives", 3).equalities(
            DMatrix::from_row_slice(2, 3, &[1.0, 0.0, 0.0, 0.0, 1.0, 0.0]),
            DVector::from_vec(vec![5.0, 5.0]),
        );
        let t3 = Task::new("three", 3).equalities(
            DMatrix::from_row_slice(1, 3, &[0.0, 0.0, 1.0]),
            DVector::from_vec(vec![3.0]),
        );
        let sol = solver(3).solve(&[t1, t2, t3]).unwrap();
        assert!((sol.x[0] + sol.x[1] - 1.0).abs() < 1e-8);
        assert!((sol.x[0] - 0.5).abs() < 1e-6 && (sol.x[1] - 0.5).abs() < 1e-6);
        assert!((sol.x[2] - 3.0).abs() < 1e-6);
        assert_eq!(sol.levels[0].freedom_left, 2);
        assert_eq!(sol.levels[1].freedom_left, 1);
    }

    #[test]
    fn inequality_above_equality_uses_the_qp() {
        // level 1: x0 <= 1; level 2: x0 = 3, x1 = 2
        let t1 = Task::new("bound", 2).inequalities(
            DMatrix::from_row_slice(1, 2, &[1.0, 0.0]),
            DVector::from_vec(vec![1.0]),
        );
        let t2 = Task::new("target", 2)
            .equalities(DMatrix::identity(2, 2), DVector::from_vec(vec![3.0, 2.0]));
        let sol = solver(2).solve(&[t1, t2]).unwrap();
        assert!((sol.x[0] - 1.0).abs() < 1e-6, "{}", sol.x);
        assert!((sol.x[1] - 2.0).abs() < 1e-6);
        assert_eq!(sol.levels[1].method, LevelMethod::Qp);
        assert_eq!(sol.levels[0].method, LevelMethod::LeastSquares);
    }

    #[test]
    fn infeasible_inequalities_get_least_squares_slacks() {
        // x0 <= -1 and -x0 <= -1 (x0 >= 1) at one level: the slacks split the violation
        let t1 = Task::new("conflict", 1).inequalities(
            DMatrix::from_row_slice(2, 1, &[1.0, -1.0]),
            DVector::from_vec(vec![-1.0, -1.0]),
        );
        let sol = solver(1).solve(&[t1]).unwrap();
        assert!(sol.x[0].abs() < 1e-6);
        assert!((sol.levels[0].slacks[0] - 1.0).abs() < 1e-6);
    }

    #[test]
    fn bad_input_is_an_error() {
        let t = Task::new("nan", 2).equalities(
            DMatrix::from_row_slice(1, 2, &[f64::NAN, 0.0]),
            DVector::from_vec(vec![0.0]),
        );
        assert_eq!(
            solver(2).solve(&[t]),
            Err(HqpError::NonFinite { task: "nan" })
        );
        let t = Task::new("dims", 2).equalities(DMatrix::zeros(1, 3), DVector::zeros(1));
        assert_eq!(
            solver(2).solve(&[t]),
            Err(HqpError::Dimensions { task: "dims" })
        );
    }

    fn task_strategy(n: usize) -> impl Strategy<Value = TaskSpec> {
        (0usize..=3, 0usize..=4).prop_flat_map(move |(me, mi)| {
            (
                proptest::collection::vec(-2.0..2.0f64, me * n),
                proptest::collection::vec(-3.0..3.0f64, me),
                proptest::collection::vec(-2.0..2.0f64, mi * n),
                proptest::collection::vec(-1.0..3.0f64, mi),
                Just(me),
                Just(mi),
            )
        })
    }

    type TaskSpec = (Vec<f64>, Vec<f64>, Vec<f64>, Vec<f64>, usize, usize);

    fn tasks_from(specs: &[TaskSpec], n: usize) -> Vec<Task> {
        specs
            .iter()
            .map(|(a, b, d, f, me, mi)| {
                Task::new("random", n)
                    .equalities(
                        DMatrix::from_row_slice(*me, n, a),
                        DVector::from_vec(b.clone()),
                    )
                    .inequalities(
                        DMatrix::from_row_slice(*mi, n, d),
                        DVector::from_vec(f.clone()),
                    )
            })
            .collect()
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]
        /// A lower level never violates a higher one: the final x keeps every higher level's
        /// inequalities within its optimal slacks and its equality residual at its optimum.
        #[test]
        fn lower_levels_never_violate_higher(specs in proptest::collection::vec(task_strategy(4), 1..5)) {
            let n = 4;
            let tasks = tasks_from(&specs, n);
            let full = solver(n).solve(&tasks).unwrap();
            for (p, t) in tasks.iter().enumerate() {
                // level p's optimum (slacks, residual) as recorded when it was solved
                let lvl = &full.levels[p];
                let final_viol = &t.d * &full.x - &t.f;
                for (i, v) in final_viol.iter().enumerate() {
                    prop_assert!(*v <= lvl.slacks[i] + 1e-5 * (1.0 + lvl.slacks[i]),
                        "level {p} row {i}: {v} > slack {}", lvl.slacks[i]);
                }
                let final_res = (&t.a * &full.x - &t.b).norm();
                prop_assert!(final_res <= lvl.equality_residual + 1e-5 * (1.0 + lvl.equality_residual),
                    "level {p}: residual {final_res} > {}", lvl.equality_residual);
            }
        }

        /// The active-set method against clarabel on whole hierarchies: with the method
        /// disabled (no iteration allowed) every level's QP falls back to clarabel, and both
        /// cascades reach the same top-level optimum (slacks and residual). Random
        /// hierarchies may send a level to the clarabel fallback (`LevelMethod::QpFallback`);
        /// that is the designed safety path and is not an error here.
        #[test]
        fn active_set_cascade_matches_clarabel(specs in proptest::collection::vec(task_strategy(6), 1..6)) {
            let n = 6;
            let tasks = tasks_from(&specs, n);
            let fast = solver(n).solve(&tasks).unwrap();
            let clarabel_only = HqpSettings {
                active_set: ActiveSetSettings { max_iterations: 0, ..ActiveSetSettings::default() },
                ..HqpSettings::default()
            };
            // The reference itself can fail (clarabel's iteration cap on a badly scaled random
            // hierarchy): such a case compares nothing.
            let reference = HierarchicalSolver::new(n, clarabel_only).solve(&tasks);
            prop_assume!(reference.is_ok(), "clarabel failed: {:?}", reference.as_ref().err());
            let reference = reference.unwrap();
            let norm = |v: &[f64]| v.iter().map(|s| s * s).sum::<f64>().sqrt();
            // The top level is the same QP for both; clarabel's interior point stops up to
            // about 1e-4 short of its optimum. Lower levels depend on the slacks the levels
            // above kept, so only the top level's optimum is compared here (each level's QP
            // alone is compared with clarabel in `control::qp`'s tests). Known gap: on one
            // random 3-level hierarchy (proptest-regressions/control/hqp.txt) the active-set
            // cascade keeps level 2's slacks at 9.1e-4 where clarabel's reach 3.5e-4.
            let (top, top_ref) = (&fast.levels[0], &reference.levels[0]);
            let (sl, sr) = (norm(&top.slacks), norm(&top_ref.slacks));
            prop_assert!((sl - sr).abs() <= 1e-4 * (1.0 + sr), "top level: slacks {sl} vs clarabel {sr}");
            let (el, er) = (top.equality_residual, top_ref.equality_residual);
            prop_assert!((el - er).abs() <= 1e-4 * (1.0 + er), "top level: residual {el} vs clarabel {er}");
        }

        /// With a single level the cascade is an ordinary (regularised) least-squares problem.
        #[test]
        fn single_equality_level_is_least_squares(a in proptest::collection::vec(-2.0..2.0f64, 12), b in proptest::collection::vec(-2.0..2.0f64, 3)) {
            let am = DMatrix::from_row_slice(3, 4, &a);
            let bv = DVector::from_vec(b);
            let sol = solver(4).solve(&[Task::new("ls", 4).equalities(am.clone(), bv.clone())]).unwrap();
            // normal equations hold: A^T (A x - b) ~ 0 (up to the tiny regularisation)
            let g = am.transpose() * (&am * &sol.x - &bv);
            prop_assert!(g.norm() < 1e-6 * (1.0 + sol.x.norm()));
        }
    }
}
