//! Descriptors and their matching.
//!
//! Two kinds of descriptors flow through dhptam: float rows from the learned extractors
//! (SuperPoint, R2D2, SIFT), compared by Euclidean distance — for unit-norm rows it lies in
//! [0, 2] and relates to the cosine by d² = 2 − 2 cos — and binary rows from ORB, compared by
//! Hamming distance (bits that differ). [`Descriptors`] borrows an N×width row-major block
//! where it lies (a numpy array handed over by the binding, a keyframe's storage);
//! [`OwnedDescriptors`] keeps rows that must outlive their frame.
//!
//! [`match_descriptors`] is the brute-force matcher (mutual nearest neighbour with a ratio
//! test, parallel over query rows); [`best_two`] serves the guided searches of tracking, where
//! the candidates come from a projection window instead of the whole set.

use rayon::prelude::*;

use crate::error::{Error, Result};

/// How descriptors compare.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum DescriptorKind {
    /// `f32` rows, Euclidean distance (in [0, 2] for unit-norm rows).
    Float,
    /// Packed bit rows, Hamming distance in bits.
    Binary,
}

impl DescriptorKind {
    /// The name used in messages and files: `"float"` or `"binary"`.
    pub fn name(self) -> &'static str {
        match self {
            DescriptorKind::Float => "float",
            DescriptorKind::Binary => "binary",
        }
    }
}

/// One borrowed descriptor row.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Descriptor<'a> {
    /// A float row.
    Float(&'a [f32]),
    /// A packed binary row.
    Binary(&'a [u8]),
}

impl Descriptor<'_> {
    /// The row's kind.
    pub fn kind(&self) -> DescriptorKind {
        match self {
            Descriptor::Float(_) => DescriptorKind::Float,
            Descriptor::Binary(_) => DescriptorKind::Binary,
        }
    }

    /// An owned copy of the row.
    pub fn to_owned(&self) -> OwnedDescriptor {
        match *self {
            Descriptor::Float(r) => OwnedDescriptor::Float(r.to_vec()),
            Descriptor::Binary(r) => OwnedDescriptor::Binary(r.to_vec()),
        }
    }
}

/// One owned descriptor row (a map point's representative descriptor, say).
#[derive(Clone, Debug, PartialEq)]
pub enum OwnedDescriptor {
    /// A float row.
    Float(Vec<f32>),
    /// A packed binary row.
    Binary(Vec<u8>),
}

impl OwnedDescriptor {
    /// The row borrowed.
    pub fn view(&self) -> Descriptor<'_> {
        match self {
            OwnedDescriptor::Float(r) => Descriptor::Float(r),
            OwnedDescriptor::Binary(r) => Descriptor::Binary(r),
        }
    }
}

/// Euclidean distance between float rows, Hamming distance (bits) between binary rows;
/// `f32::INFINITY` when the kinds or widths differ, so a mismatch never matches.
#[inline(always)]
pub fn distance(a: Descriptor<'_>, b: Descriptor<'_>) -> f32 {
    match (a, b) {
        (Descriptor::Float(a), Descriptor::Float(b)) if a.len() == b.len() => l2(a, b),
        (Descriptor::Binary(a), Descriptor::Binary(b)) if a.len() == b.len() => hamming(a, b),
        _ => f32::INFINITY,
    }
}

#[inline(always)]
fn l2(a: &[f32], b: &[f32]) -> f32 {
    // Four independent accumulators let the compiler keep several lanes busy.
    let mut acc = [0.0f32; 4];
    let (ca, ra) = a.split_at(a.len() & !3);
    let (cb, rb) = b.split_at(ca.len());
    for (x, y) in ca.chunks_exact(4).zip(cb.chunks_exact(4)) {
        for k in 0..4 {
            let d = x[k] - y[k];
            acc[k] += d * d;
        }
    }
    let tail: f32 = ra.iter().zip(rb).map(|(x, y)| (x - y) * (x - y)).sum();
    (acc[0] + acc[1] + acc[2] + acc[3] + tail).sqrt()
}

#[inline(always)]
fn hamming(a: &[u8], b: &[u8]) -> f32 {
    let (ca, ra) = a.split_at(a.len() & !7);
    let (cb, rb) = b.split_at(ca.len());
    let mut bits: u32 = ca
        .chunks_exact(8)
        .zip(cb.chunks_exact(8))
        .map(|(x, y)| {
            let x = u64::from_le_bytes(x.try_into().unwrap_or([0; 8]));
            let y = u64::from_le_bytes(y.try_into().unwrap_or([0; 8]));
            (x ^ y).count_ones()
        })
        .sum();
    bits += ra
        .iter()
        .zip(rb)
        .map(|(x, y)| (x ^ y).count_ones())
        .sum::<u32>();
    bits as f32
}

/// An N×width block of descriptor rows, borrowed where it lies (row-major).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Descriptors<'a> {
    /// Float rows of `dim` values each.
    Float {
        /// Values per row.
        dim: usize,
        /// N·dim values.
        data: &'a [f32],
    },
    /// Binary rows of `bytes` bytes each.
    Binary {
        /// Bytes per row.
        bytes: usize,
        /// N·bytes bytes.
        data: &'a [u8],
    },
}

impl<'a> Descriptors<'a> {
    /// Float rows of `dim` values; `data.len()` must be a multiple of `dim > 0`.
    pub fn float(data: &'a [f32], dim: usize) -> Result<Self> {
        check_width("descriptors", data.len(), dim)?;
        Ok(Descriptors::Float { dim, data })
    }

    /// Binary rows of `bytes` bytes; `data.len()` must be a multiple of `bytes > 0`.
    pub fn binary(data: &'a [u8], bytes: usize) -> Result<Self> {
        check_width("descriptors", data.len(), bytes)?;
        Ok(Descriptors::Binary { bytes, data })
    }

    /// Number of rows.
    pub fn len(&self) -> usize {
        match *self {
            Descriptors::Float { dim, data } => data.len() / dim.max(1),
            Descriptors::Binary { bytes, data } => data.len() / bytes.max(1),
        }
    }

    /// Whether there are no rows.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The kind of the rows.
    pub fn kind(&self) -> DescriptorKind {
        match self {
            Descriptors::Float { .. } => DescriptorKind::Float,
            Descriptors::Binary { .. } => DescriptorKind::Binary,
        }
    }

    /// Values (float) or bytes (binary) per row.
    pub fn width(&self) -> usize {
        match *self {
            Descriptors::Float { dim, .. } => dim,
            Descriptors::Binary { bytes, .. } => bytes,
        }
    }

    /// Row `i`; panics when `i >= len()`, like slice indexing.
    pub fn row(&self, i: usize) -> Descriptor<'a> {
        match *self {
            Descriptors::Float { dim, data } => Descriptor::Float(&data[i * dim..(i + 1) * dim]),
            Descriptors::Binary { bytes, data } => {
                Descriptor::Binary(&data[i * bytes..(i + 1) * bytes])
            }
        }
    }

    /// An owned copy of all rows.
    pub fn to_owned(&self) -> OwnedDescriptors {
        match *self {
            Descriptors::Float { dim, data } => OwnedDescriptors {
                kind: DescriptorKind::Float,
                width: dim,
                float: data.to_vec(),
                binary: Vec::new(),
            },
            Descriptors::Binary { bytes, data } => OwnedDescriptors {
                kind: DescriptorKind::Binary,
                width: bytes,
                float: Vec::new(),
                binary: data.to_vec(),
            },
        }
    }
}

fn check_width(what: &str, len: usize, width: usize) -> Result<()> {
    if width == 0 || len % width != 0 {
        return Err(Error::invalid(
            what,
            format!("a whole number of rows of width {width} (> 0)"),
            format!("{len} values"),
        ));
    }
    Ok(())
}

/// Descriptor rows owned in one contiguous block.
#[derive(Clone, Debug, PartialEq)]
pub struct OwnedDescriptors {
    kind: DescriptorKind,
    width: usize,
    float: Vec<f32>,
    binary: Vec<u8>,
}

impl OwnedDescriptors {
    /// No rows yet, of the given kind and width (values or bytes per row).
    pub fn new(kind: DescriptorKind, width: usize) -> Self {
        Self {
            kind,
            width,
            float: Vec::new(),
            binary: Vec::new(),
        }
    }

    /// The rows borrowed.
    pub fn view(&self) -> Descriptors<'_> {
        match self.kind {
            DescriptorKind::Float => Descriptors::Float {
                dim: self.width,
                data: &self.float,
            },
            DescriptorKind::Binary => Descriptors::Binary {
                bytes: self.width,
                data: &self.binary,
            },
        }
    }

    /// Number of rows.
    pub fn len(&self) -> usize {
        self.view().len()
    }

    /// Whether there are no rows.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The kind of the rows.
    pub fn kind(&self) -> DescriptorKind {
        self.kind
    }

    /// Values (float) or bytes (binary) per row.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Appends one row; it must have this block's kind and width.
    pub fn push(&mut self, row: Descriptor<'_>) -> Result<()> {
        match row {
            Descriptor::Float(r) if self.kind == DescriptorKind::Float && r.len() == self.width => {
                self.float.extend_from_slice(r)
            }
            Descriptor::Binary(r)
                if self.kind == DescriptorKind::Binary && r.len() == self.width =>
            {
                self.binary.extend_from_slice(r)
            }
            _ => {
                return Err(Error::invalid(
                    "descriptor",
                    format!("a {} row of width {}", self.kind.name(), self.width),
                    format!("a {} row of width {}", row.kind().name(), row_width(row)),
                ))
            }
        }
        Ok(())
    }

    /// The rows at `indices`, in that order; panics on an index out of range.
    pub fn select(&self, indices: &[usize]) -> Self {
        let mut out = Self::new(self.kind, self.width);
        let view = self.view();
        for &i in indices {
            match view.row(i) {
                Descriptor::Float(r) => out.float.extend_from_slice(r),
                Descriptor::Binary(r) => out.binary.extend_from_slice(r),
            }
        }
        out
    }
}

fn row_width(row: Descriptor<'_>) -> usize {
    match row {
        Descriptor::Float(r) => r.len(),
        Descriptor::Binary(r) => r.len(),
    }
}

/// Acceptance rules of [`match_descriptors`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MatchOptions {
    /// Largest accepted distance (Euclidean, or Hamming bits).
    pub max_distance: f32,
    /// Ratio test: accept only when best < ratio · second best; 1 turns the test off.
    pub ratio: f32,
    /// Keep a pair only when each row is the other's nearest neighbour.
    pub mutual: bool,
}

impl MatchOptions {
    /// Defaults that mean the same for each kind: for unit-norm float rows 0.9 (cosine ≥ 0.6),
    /// for 256-bit ORB rows 64 bits (a quarter of the bits), ratio 0.9, mutual.
    pub fn for_kind(kind: DescriptorKind) -> Self {
        let max_distance = match kind {
            DescriptorKind::Float => 0.9,
            DescriptorKind::Binary => 64.0,
        };
        Self {
            max_distance,
            ratio: 0.9,
            mutual: true,
        }
    }
}

/// One accepted pair of rows.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Match {
    /// Row in the query block.
    pub query: u32,
    /// Row in the train block.
    pub train: u32,
    /// Their distance.
    pub distance: f32,
}

/// The nearest and second-nearest train rows to `query` among `candidates`:
/// `(best index, best distance, second distance)`, the second `f32::INFINITY` when there is
/// one candidate; `None` when there are none.
///
/// On x86-64 CPUs with POPCNT (every one since about 2008) the search runs in a copy compiled
/// for it, so the Hamming distances of binary descriptors count bits in one instruction per
/// 64 bits; the portable build's baseline has no such instruction.
pub fn best_two<I: IntoIterator<Item = usize>>(
    query: Descriptor<'_>,
    train: Descriptors<'_>,
    candidates: I,
) -> Option<(usize, f32, f32)> {
    #[cfg(target_arch = "x86_64")]
    if matches!(query, Descriptor::Binary(_)) && std::arch::is_x86_feature_detected!("popcnt") {
        // SAFETY: the CPU supports POPCNT, checked just above.
        return unsafe { best_two_popcnt(query, train, candidates) };
    }
    best_two_plain(query, train, candidates)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "popcnt")]
unsafe fn best_two_popcnt<I: IntoIterator<Item = usize>>(
    query: Descriptor<'_>,
    train: Descriptors<'_>,
    candidates: I,
) -> Option<(usize, f32, f32)> {
    best_two_plain(query, train, candidates)
}

#[inline(always)]
fn best_two_plain<I: IntoIterator<Item = usize>>(
    query: Descriptor<'_>,
    train: Descriptors<'_>,
    candidates: I,
) -> Option<(usize, f32, f32)> {
    match (query, train) {
        // 256-bit rows (ORB): the query's four words loaded once, each train row's read
        // straight from the block (the `matching` criterion bench, docs/BENCHMARKS.md).
        (Descriptor::Binary(q), Descriptors::Binary { bytes: 32, data }) if q.len() == 32 => {
            let w = words(q);
            nearest_two(candidates, |j| {
                let r = words(&data[j * 32..(j + 1) * 32]);
                ((w[0] ^ r[0]).count_ones()
                    + (w[1] ^ r[1]).count_ones()
                    + (w[2] ^ r[2]).count_ones()
                    + (w[3] ^ r[3]).count_ones()) as f32
            })
        }
        // Other binary widths, likewise straight from the block's bytes.
        (Descriptor::Binary(q), Descriptors::Binary { bytes, data }) if q.len() == bytes => {
            nearest_two(candidates, |j| {
                hamming(q, &data[j * bytes..(j + 1) * bytes])
            })
        }
        _ => nearest_two(candidates, |j| distance(query, train.row(j))),
    }
}

/// A 256-bit row as four little-endian words.
#[inline(always)]
fn words(row: &[u8]) -> [u64; 4] {
    let word = |k: usize| {
        let mut b = [0u8; 8];
        b.copy_from_slice(&row[8 * k..8 * k + 8]);
        u64::from_le_bytes(b)
    };
    [word(0), word(1), word(2), word(3)]
}

/// The two smallest of `distance(j)` over `candidates`, as [`best_two`] returns them.
#[inline(always)]
fn nearest_two<I: IntoIterator<Item = usize>>(
    candidates: I,
    distance: impl Fn(usize) -> f32,
) -> Option<(usize, f32, f32)> {
    let mut best: Option<(usize, f32)> = None;
    let mut second = f32::INFINITY;
    for j in candidates {
        let d = distance(j);
        match best {
            Some((_, b)) if d >= b => second = second.min(d),
            Some((_, b)) => {
                second = b;
                best = Some((j, d));
            }
            None => best = Some((j, d)),
        }
    }
    best.map(|(j, d)| (j, d, second))
}

/// Brute-force matching of every query row against every train row: nearest neighbour under
/// `max_distance`, passing the ratio test, and mutual when asked. Pairs come sorted by query
/// row. Runs in parallel over query rows.
pub fn match_descriptors(
    query: Descriptors<'_>,
    train: Descriptors<'_>,
    options: &MatchOptions,
) -> Result<Vec<Match>> {
    if query.kind() != train.kind() || query.width() != train.width() {
        return Err(Error::invalid(
            "train descriptors",
            format!("{} rows of width {}", query.kind().name(), query.width()),
            format!("{} rows of width {}", train.kind().name(), train.width()),
        ));
    }
    let valid = options.max_distance >= 0.0 && options.ratio > 0.0 && options.ratio <= 1.0;
    if !valid {
        return Err(Error::invalid(
            "match options",
            "max_distance ≥ 0 and 0 < ratio ≤ 1",
            format!("{options:?}"),
        ));
    }
    let nearest = |a: Descriptors<'_>, b: Descriptors<'_>| -> Vec<Option<(usize, f32, f32)>> {
        (0..a.len())
            .into_par_iter()
            .with_min_len(16)
            .map(|i| best_two(a.row(i), b, 0..b.len()))
            .collect()
    };
    let forward = nearest(query, train);
    let backward = if options.mutual {
        nearest(train, query)
    } else {
        Vec::new()
    };
    let matches = forward
        .iter()
        .enumerate()
        .filter_map(|(i, hit)| {
            let (j, d, second) = (*hit)?;
            let passes = d <= options.max_distance
                && (options.ratio >= 1.0 || d < options.ratio * second)
                && (!options.mutual || matches!(backward[j], Some((back, _, _)) if back == i));
            passes.then_some(Match {
                query: i as u32,
                train: j as u32,
                distance: d,
            })
        })
        .collect();
    Ok(matches)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{rngs::StdRng, Rng, SeedableRng};

    fn unit_rows(rng: &mut StdRng, n: usize, dim: usize) -> Vec<f32> {
        let mut data = Vec::with_capacity(n * dim);
        for _ in 0..n {
            let row: Vec<f32> = (0..dim).map(|_| rng.random::<f32>() - 0.5).collect();
            let norm = row.iter().map(|v| v * v).sum::<f32>().sqrt();
            data.extend(row.iter().map(|v| v / norm));
        }
        data
    }

    #[test]
    fn distances_agree_with_their_definitions() {
        let mut rng = StdRng::seed_from_u64(1);
        for dim in [3usize, 64, 128, 257] {
            let a: Vec<f32> = (0..dim).map(|_| rng.random()).collect();
            let b: Vec<f32> = (0..dim).map(|_| rng.random()).collect();
            let want = a
                .iter()
                .zip(&b)
                .map(|(x, y)| ((x - y) as f64).powi(2))
                .sum::<f64>()
                .sqrt();
            let got = distance(Descriptor::Float(&a), Descriptor::Float(&b));
            assert!(
                (got as f64 - want).abs() < 1e-4 * want.max(1.0),
                "{got} vs {want}"
            );
        }
        for bytes in [1usize, 32, 61] {
            let a: Vec<u8> = (0..bytes).map(|_| rng.random()).collect();
            let b: Vec<u8> = (0..bytes).map(|_| rng.random()).collect();
            let mut want = 0;
            for (x, y) in a.iter().zip(&b) {
                for bit in 0..8 {
                    want += ((x >> bit) & 1 != (y >> bit) & 1) as u32;
                }
            }
            assert_eq!(
                distance(Descriptor::Binary(&a), Descriptor::Binary(&b)),
                want as f32
            );
        }
        let f = [0.0f32; 4];
        let u = [0u8; 4];
        assert_eq!(
            distance(Descriptor::Float(&f), Descriptor::Binary(&u)),
            f32::INFINITY
        );
        assert_eq!(
            distance(Descriptor::Float(&f), Descriptor::Float(&f[..3])),
            f32::INFINITY
        );
    }

    #[test]
    fn noisy_copies_match_their_originals_and_strangers_do_not() {
        let mut rng = StdRng::seed_from_u64(7);
        let (n, dim) = (200, 128);
        let train = unit_rows(&mut rng, n, dim);
        // Queries: the first 150 train rows with noise, in reverse order, then 50 strangers.
        let mut query = Vec::new();
        let mut truth = Vec::new();
        for i in (0..150).rev() {
            let row: Vec<f32> = train[i * dim..(i + 1) * dim]
                .iter()
                .map(|v| v + 0.02 * (rng.random::<f32>() - 0.5))
                .collect();
            let norm = row.iter().map(|v| v * v).sum::<f32>().sqrt();
            query.extend(row.iter().map(|v| v / norm));
            truth.push(i as u32);
        }
        query.extend(unit_rows(&mut rng, 50, dim));
        let q = Descriptors::float(&query, dim).unwrap();
        let t = Descriptors::float(&train, dim).unwrap();
        let options = MatchOptions {
            max_distance: 0.5,
            ratio: 0.8,
            mutual: true,
        };
        let matches = match_descriptors(q, t, &options).unwrap();
        assert_eq!(matches.len(), 150);
        for m in &matches {
            assert_eq!(m.train, truth[m.query as usize]);
            assert!(m.distance < 0.1);
        }
        assert!(matches.windows(2).all(|w| w[0].query < w[1].query));
    }

    #[test]
    fn ratio_and_mutual_checks_reject_ambiguous_pairs() {
        // Two identical train rows: the ratio test must refuse both.
        let a = [1.0f32, 0.0];
        let train = [1.0f32, 0.0, 1.0, 0.0, 0.0, 1.0];
        let q = Descriptors::float(&a, 2).unwrap();
        let t = Descriptors::float(&train, 2).unwrap();
        let strict = MatchOptions {
            max_distance: 2.0,
            ratio: 0.9,
            mutual: false,
        };
        assert!(match_descriptors(q, t, &strict).unwrap().is_empty());
        let loose = MatchOptions {
            ratio: 1.0,
            ..strict
        };
        assert_eq!(match_descriptors(q, t, &loose).unwrap().len(), 1);
        // Mutual: two queries near the same train row; only the nearer one keeps it.
        let queries = [1.0f32, 0.0, 0.9, 0.1];
        let train = [1.0f32, 0.0];
        let q = Descriptors::float(&queries, 2).unwrap();
        let t = Descriptors::float(&train, 2).unwrap();
        let mutual = MatchOptions {
            mutual: true,
            ..loose
        };
        let m = match_descriptors(q, t, &mutual).unwrap();
        assert_eq!(m.len(), 1);
        assert_eq!(m[0].query, 0);
        let one_way = MatchOptions {
            mutual: false,
            ..loose
        };
        assert_eq!(match_descriptors(q, t, &one_way).unwrap().len(), 2);
    }

    #[test]
    fn binary_rows_match_by_hamming_distance() {
        let mut rng = StdRng::seed_from_u64(3);
        let train: Vec<u8> = (0..64 * 32).map(|_| rng.random()).collect();
        let mut query = train.clone();
        for row in query.chunks_mut(32) {
            row[0] ^= 0b101; // two bits flipped
        }
        let q = Descriptors::binary(&query, 32).unwrap();
        let t = Descriptors::binary(&train, 32).unwrap();
        let m = match_descriptors(q, t, &MatchOptions::for_kind(DescriptorKind::Binary)).unwrap();
        assert_eq!(m.len(), 64);
        assert!(m.iter().all(|m| m.query == m.train && m.distance == 2.0));
    }

    #[test]
    fn best_two_orders_candidates_and_handles_edge_cases() {
        let train = [0.0f32, 0.0, 3.0, 0.0, 1.0, 0.0, 2.0, 0.0];
        let t = Descriptors::float(&train, 2).unwrap();
        let q = Descriptor::Float(&[0.9, 0.0]);
        let (j, d, s) = best_two(q, t, 0..4).unwrap();
        assert_eq!(j, 2);
        assert!((d - 0.1).abs() < 1e-6 && (s - 0.9).abs() < 1e-6);
        let (j, _, s) = best_two(q, t, [3]).unwrap();
        assert_eq!((j, s), (3, f32::INFINITY));
        assert!(best_two(q, t, []).is_none());
    }

    #[test]
    fn binary_best_two_agrees_with_the_bit_count_at_every_width() {
        // 256-bit rows take their own path (and POPCNT where the CPU has it); every width
        // must give the nearest two by a plain count of differing bits, the first candidate
        // on ties.
        let mut state = 0x2545_f491_4f6c_dd1d_u64;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        for bytes in [32usize, 8, 13, 64] {
            let rows = 300;
            let train: Vec<u8> = (0..rows * bytes).map(|_| next() as u8).collect();
            let t = Descriptors::binary(&train, bytes).unwrap();
            for _ in 0..20 {
                let q: Vec<u8> = (0..bytes).map(|_| next() as u8).collect();
                let bits = |j: usize| -> u32 {
                    q.iter()
                        .zip(&train[j * bytes..(j + 1) * bytes])
                        .map(|(a, b)| (a ^ b).count_ones())
                        .sum()
                };
                let mut order: Vec<(u32, usize)> = (0..rows).map(|j| (bits(j), j)).collect();
                order.sort();
                let got = best_two(Descriptor::Binary(&q), t, 0..rows).unwrap();
                assert_eq!(
                    got,
                    (order[0].1, order[0].0 as f32, order[1].0 as f32),
                    "{bytes} bytes"
                );
                // A subset of candidates, in a given order: the first of the nearest wins.
                let some = [7usize, 3, 250, 3];
                let least = some.iter().map(|&j| bits(j)).min().unwrap();
                let first = some.into_iter().find(|&j| bits(j) == least).unwrap();
                assert_eq!(best_two(Descriptor::Binary(&q), t, some).unwrap().0, first);
            }
        }
    }

    #[test]
    fn bad_shapes_and_kinds_are_refused() {
        assert!(Descriptors::float(&[0.0; 5], 2).is_err());
        assert!(Descriptors::binary(&[0; 4], 0).is_err());
        let f = [0.0f32; 4];
        let b = [0u8; 4];
        let err = match_descriptors(
            Descriptors::float(&f, 2).unwrap(),
            Descriptors::binary(&b, 2).unwrap(),
            &MatchOptions::for_kind(DescriptorKind::Float),
        )
        .unwrap_err();
        assert!(err.to_string().contains("binary rows of width 2"), "{err}");
        let mut owned = OwnedDescriptors::new(DescriptorKind::Float, 2);
        owned.push(Descriptor::Float(&[1.0, 2.0])).unwrap();
        assert!(owned.push(Descriptor::Float(&[1.0])).is_err());
        assert!(owned.push(Descriptor::Binary(&[1, 2])).is_err());
        owned.push(Descriptor::Float(&[3.0, 4.0])).unwrap();
        let picked = owned.select(&[1, 0]);
        assert_eq!(picked.view().row(0), Descriptor::Float(&[3.0, 4.0]));
        assert_eq!(picked.len(), 2);
    }
}
