//! Symmetric positive-definite systems with a block sparsity pattern, as the reduced camera
//! system of bundle adjustment and the normal equations of a pose graph produce them.
//!
//! Values live block by block (upper triangle, each block b×b column-major) so assembly can
//! add whole blocks; a solve scatters them either into a dense matrix (faer's blocked dense
//! Cholesky, for small systems) or into a compressed-column upper triangle whose symbolic
//! Cholesky factorisation (block AMD ordering, supernodal: the dense blocks make the supernodes)
//! is computed once per pattern and reused by every numeric factorisation.

use std::collections::HashMap;

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::cholesky::llt::factor::LltRegularization;
use faer::sparse::linalg::cholesky::{
    factorize_symbolic_cholesky, CholeskySymbolicParams, SymbolicCholesky, SymmetricOrdering,
};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMat};
use faer::{Conj, Mat, MatMut, Par, Side};

use crate::error::{Error, Result};

/// How the block system is factorised.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum LinearSolver {
    /// Dense below [`DENSE_LIMIT`] unknowns, sparse above.
    #[default]
    Auto,
    /// Dense Cholesky of the full matrix.
    Dense,
    /// Sparse Cholesky with the symbolic factorisation reused.
    Sparse,
}

/// Largest system [`LinearSolver::Auto`] factorises densely.
pub const DENSE_LIMIT: usize = 1500;

/// The block pattern: `n` block rows/columns of size `b`, and the upper-triangle blocks (i ≤ k).
#[derive(Debug)]
pub struct BlockPattern {
    n: usize,
    b: usize,
    /// Upper blocks (row i, column k), sorted by column then row; the diagonal is always there.
    blocks: Vec<(usize, usize)>,
    lookup: HashMap<(usize, usize), usize>,
}

impl BlockPattern {
    /// The pattern with every diagonal block plus the given off-diagonal pairs (either order).
    pub fn new(n: usize, b: usize, pairs: impl IntoIterator<Item = (usize, usize)>) -> Self {
        let mut blocks: Vec<(usize, usize)> = (0..n).map(|i| (i, i)).collect();
        blocks.extend(pairs.into_iter().map(|(i, k)| (i.min(k), i.max(k))));
        blocks.sort_unstable_by_key(|&(i, k)| (k, i));
        blocks.dedup();
        let lookup = blocks.iter().enumerate().map(|(s, &ik)| (ik, s)).collect();
        Self {
            n,
            b,
            blocks,
            lookup,
        }
    }

    /// Number of block rows.
    pub fn block_count(&self) -> usize {
        self.n
    }

    /// Block size.
    pub fn block_size(&self) -> usize {
        self.b
    }

    /// Number of stored (upper) blocks.
    pub fn stored_blocks(&self) -> usize {
        self.blocks.len()
    }

    /// Scalar dimension n·b.
    pub fn dim(&self) -> usize {
        self.n * self.b
    }

    /// Slot of block (i, k) with i ≤ k, if it is in the pattern.
    pub fn slot(&self, i: usize, k: usize) -> Option<usize> {
        self.lookup.get(&(i, k)).copied()
    }

    /// Slot of the diagonal block i.
    pub fn diagonal_slot(&self, i: usize) -> usize {
        self.lookup[&(i, i)]
    }

    /// A zeroed value array for this pattern.
    pub fn zeros(&self) -> Vec<f64> {
        vec![0.0; self.blocks.len() * self.b * self.b]
    }
}

/// Approximate-minimum-degree order of the block graph: (forward, inverse) permutations.
fn block_amd(pattern: &BlockPattern) -> Result<(Vec<usize>, Vec<usize>)> {
    let n = pattern.n;
    let mut col_ptr = Vec::with_capacity(n + 1);
    let mut row_idx = Vec::with_capacity(pattern.blocks.len());
    col_ptr.push(0usize);
    let mut s = 0;
    for k in 0..n {
        while s < pattern.blocks.len() && pattern.blocks[s].1 == k {
            row_idx.push(pattern.blocks[s].0);
            s += 1;
        }
        col_ptr.push(row_idx.len());
    }
    let nnz = row_idx.len();
    let graph = SymbolicSparseColMat::new_checked(n, n, col_ptr, None, row_idx);
    let mut fwd = vec![0usize; n];
    let mut inv = vec![0usize; n];
    let mut mem = MemBuffer::new(faer::sparse::linalg::amd::order_scratch::<usize>(n, nnz));
    faer::sparse::linalg::amd::order(
        &mut fwd,
        &mut inv,
        graph.as_ref(),
        Default::default(),
        MemStack::new(&mut mem),
    )
    .map_err(|e| Error::numerical("block ordering", format!("{e:?}")))?;
    Ok((fwd, inv))
}

/// A reusable factorisation workspace for one [`BlockPattern`].
pub struct BlockCholesky {
    dense: bool,
    parallelism: Par,
    // Sparse path: the scalar upper-triangle pattern, where each entry comes from in the block
    // values, and the symbolic factorisation.
    csc: Option<SymbolicSparseColMat<usize>>,
    gather: Vec<usize>,
    csc_values: Vec<f64>,
    symbolic: Option<SymbolicCholesky<usize>>,
    l_values: Vec<f64>,
    buffer: Option<MemBuffer>,
    dense_matrix: Mat<f64>,
}

impl BlockCholesky {
    /// Prepares the factorisation for `pattern`: the symbolic analysis happens here, once.
    pub fn new(pattern: &BlockPattern, solver: LinearSolver, threads: usize) -> Result<Self> {
        let dim = pattern.dim();
        let dense = match solver {
            LinearSolver::Auto => dim <= DENSE_LIMIT,
            LinearSolver::Dense => true,
            LinearSolver::Sparse => false,
        };
        let parallelism = if threads > 1 {
            Par::rayon(threads)
        } else {
            Par::Seq
        };
        let mut this = Self {
            dense,
            parallelism,
            csc: None,
            gather: Vec::new(),
            csc_values: Vec::new(),
            symbolic: None,
            l_values: Vec::new(),
            buffer: None,
            dense_matrix: Mat::zeros(0, 0),
        };
        if dense {
            this.dense_matrix = Mat::zeros(dim, dim);
            return Ok(this);
        }
        let b = pattern.b;
        let mut col_ptr = Vec::with_capacity(dim + 1);
        let mut row_idx = Vec::new();
        let mut gather = Vec::new();
        col_ptr.push(0usize);
        let mut first = 0;
        for k in 0..pattern.n {
            let mut last = first;
            while last < pattern.blocks.len() && pattern.blocks[last].1 == k {
                last += 1;
            }
            for cc in 0..b {
                for (slot, &(i, _)) in pattern.blocks[first..last].iter().enumerate() {
                    let rows = if i == k { cc + 1 } else { b };
                    for rr in 0..rows {
                        row_idx.push(i * b + rr);
                        gather.push((first + slot) * b * b + cc * b + rr);
                    }
                }
                col_ptr.push(row_idx.len());
            }
            first = last;
        }
        let csc = SymbolicSparseColMat::new_checked(dim, dim, col_ptr, None, row_idx);
        // Fill-reducing order computed on the block graph (n nodes instead of n·b) and
        // expanded to scalars, so that each block's unknowns stay together and supernodes
        // line up with blocks.
        let (block_fwd, block_inv) = block_amd(pattern)?;
        let fwd: Vec<usize> = block_fwd
            .iter()
            .flat_map(|&k| (0..b).map(move |c| k * b + c))
            .collect();
        let inv: Vec<usize> = block_inv
            .iter()
            .flat_map(|&k| (0..b).map(move |c| k * b + c))
            .collect();
        let symbolic = factorize_symbolic_cholesky(
            csc.as_ref(),
            Side::Upper,
            SymmetricOrdering::Custom(faer::perm::PermRef::new_checked(&fwd, &inv, dim)),
            CholeskySymbolicParams {
                supernodal_flop_ratio_threshold:
                    faer::sparse::linalg::SupernodalThreshold::FORCE_SUPERNODAL,
                ..Default::default()
            },
        )
        .map_err(|e| Error::numerical("sparse Cholesky analysis", format!("{e:?}")))?;
        let scratch = symbolic
            .factorize_numeric_llt_scratch::<f64>(parallelism, Default::default())
            .or(symbolic.solve_in_place_scratch::<f64>(1, parallelism));
        this.l_values = vec![0.0; symbolic.len_val()];
        this.buffer = Some(MemBuffer::new(scratch));
        this.csc_values = vec![0.0; gather.len()];
        this.gather = gather;
        this.csc = Some(csc);
        this.symbolic = Some(symbolic);
        Ok(this)
    }

    /// Whether the dense path is used.
    pub fn is_dense(&self) -> bool {
        self.dense
    }

    /// Solves A x = rhs in place, A given by its upper blocks in `values`. Returns `false`
    /// (leaving `rhs` unspecified) when A is not numerically positive definite.
    pub fn solve(&mut self, pattern: &BlockPattern, values: &[f64], rhs: &mut [f64]) -> bool {
        let dim = pattern.dim();
        let rhs_mat = MatMut::from_column_major_slice_mut(rhs, dim, 1);
        if self.dense {
            self.solve_dense(pattern, values, rhs_mat)
        } else {
            self.solve_sparse(values, rhs_mat)
        }
    }

    fn solve_dense(
        &mut self,
        pattern: &BlockPattern,
        values: &[f64],
        rhs: MatMut<'_, f64>,
    ) -> bool {
        let b = pattern.b;
        let a = &mut self.dense_matrix;
        // The previous factor's fill-in sits where the pattern has no block: clear it.
        a.fill(0.0);
        // Only the lower triangle is read by the factorisation: store block (i, k) transposed.
        for (slot, &(i, k)) in pattern.blocks.iter().enumerate() {
            let block = &values[slot * b * b..(slot + 1) * b * b];
            for cc in 0..b {
                for rr in 0..b {
                    a[(k * b + cc, i * b + rr)] = block[cc * b + rr];
                }
            }
        }
        let mut mem = MemBuffer::new(
            faer::linalg::cholesky::llt::factor::cholesky_in_place_scratch::<f64>(
                a.nrows(),
                self.parallelism,
                Default::default(),
            ),
        );
        let stack = MemStack::new(&mut mem);
        let factor = faer::linalg::cholesky::llt::factor::cholesky_in_place(
            a.as_mut(),
            LltRegularization::default(),
            self.parallelism,
            stack,
            Default::default(),
        );
        if factor.is_err() {
            return false;
        }
        faer::linalg::cholesky::llt::solve::solve_in_place_with_conj(
            a.as_ref(),
            Conj::No,
            rhs,
            self.parallelism,
            MemStack::new(&mut MemBuffer::new(faer::dyn_stack::StackReq::EMPTY)),
        );
        true
    }

    fn solve_sparse(&mut self, values: &[f64], rhs: MatMut<'_, f64>) -> bool {
        let (Some(csc), Some(symbolic), Some(buffer)) =
            (&self.csc, &self.symbolic, &mut self.buffer)
        else {
            return false;
        };
        for (dst, &src) in self.csc_values.iter_mut().zip(&self.gather) {
            *dst = values[src];
        }
        let a = SparseColMatRef::new(csc.as_ref(), &self.csc_values);
        let stack = MemStack::new(buffer);
        let factor = symbolic.factorize_numeric_llt::<f64>(
            &mut self.l_values,
            a,
            Side::Upper,
            LltRegularization::default(),
            self.parallelism,
            stack,
            Default::default(),
        );
        match factor {
            Ok(llt) => {
                llt.solve_in_place_with_conj(
                    Conj::No,
                    rhs,
                    self.parallelism,
                    MemStack::new(buffer),
                );
                true
            }
            Err(_) => false,
        }
    }
}
