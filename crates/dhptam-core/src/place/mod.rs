//! Place recognition for loop closing: one global embedding per keyframe, compared by cosine.
//!
//! The paper's keyframe embedding is the mean of the keyframe's learned descriptors,
//! normalised to unit length; two keyframes of the same place share many descriptors, so their
//! means point the same way. Binary (ORB) descriptors are first read as ±1 vectors (bit set →
//! +1, clear → −1; bit `i` of byte `b` is component `8b + i`, least significant bit first), so
//! that the mean is a per-bit majority vote and the cosine of two such vectors falls as their
//! Hamming distance grows.
//!
//! [`PlaceDatabase`] holds the embeddings of the map's keyframes by id and answers "which
//! keyframes look most like this one", skipping those the caller excludes (the query's
//! covisible neighbours). The search is exhaustive: a map holds thousands of keyframes at most,
//! and one query costs a dot product per keyframe.

use std::collections::HashMap;

use crate::error::{Error, Result};
use crate::matching::Descriptors;

/// The normalised mean of the rows (binary rows as ±1 per bit first); `None` when there are
/// no rows. A zero mean (rows that cancel exactly) gives the zero vector, which no query
/// matches.
pub fn embedding(descriptors: Descriptors<'_>) -> Option<Vec<f32>> {
    if descriptors.is_empty() {
        return None;
    }
    let n = descriptors.len();
    // Accumulate in f64: thousands of rows of f32 lose digits otherwise.
    let mut sum: Vec<f64> = match descriptors {
        Descriptors::Float { dim, data } => {
            let mut sum = vec![0.0f64; dim];
            for row in data.chunks_exact(dim) {
                for (s, &v) in sum.iter_mut().zip(row) {
                    *s += v as f64;
                }
            }
            sum
        }
        Descriptors::Binary { bytes, data } => {
            // Count set bits per position; the ±1 sum is 2·count − n.
            let mut count = vec![0u32; bytes * 8];
            for row in data.chunks_exact(bytes) {
                for (b, &byte) in row.iter().enumerate() {
                    for i in 0..8 {
                        count[8 * b + i] += ((byte >> i) & 1) as u32;
                    }
                }
            }
            count.iter().map(|&c| 2.0 * c as f64 - n as f64).collect()
        }
    };
    let norm = sum.iter().map(|v| v * v).sum::<f64>().sqrt();
    if norm > 0.0 && norm.is_finite() {
        sum.iter_mut().for_each(|v| *v /= norm);
    } else {
        sum.iter_mut().for_each(|v| *v = 0.0);
    }
    Some(sum.into_iter().map(|v| v as f32).collect())
}

/// Keyframe embeddings by id, searched by cosine similarity.
#[derive(Clone, Debug, Default)]
pub struct PlaceDatabase {
    /// Embedding length, fixed by the first [`PlaceDatabase::add`] (0 while empty).
    dim: usize,
    ids: Vec<u64>,
    /// Unit-norm rows, `dim` values each, in the order of `ids`.
    rows: Vec<f32>,
    index: HashMap<u64, usize>,
}

impl PlaceDatabase {
    /// An empty database.
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds (or replaces) the embedding of keyframe `id`. The embedding is stored normalised;
    /// it must be non-empty, finite, non-zero and as long as those already stored.
    pub fn add(&mut self, id: u64, embedding: Vec<f32>) -> Result<()> {
        if embedding.is_empty() {
            return Err(Error::invalid("embedding", "at least one value", 0));
        }
        if !self.ids.is_empty() && embedding.len() != self.dim {
            return Err(Error::invalid(
                "embedding",
                format!("{} values, as the stored embeddings", self.dim),
                embedding.len(),
            ));
        }
        if let Some(i) = embedding.iter().position(|v| !v.is_finite()) {
            return Err(Error::invalid(
                format!("embedding[{i}]"),
                "a finite number",
                embedding[i],
            ));
        }
        let norm = embedding
            .iter()
            .map(|&v| (v as f64) * (v as f64))
            .sum::<f64>()
            .sqrt();
        if norm == 0.0 {
            return Err(Error::invalid(
                "embedding",
                "a non-zero vector (cosine is undefined for zero)",
                "all zeros",
            ));
        }
        let unit = embedding.iter().map(|&v| (v as f64 / norm) as f32);
        if self.ids.is_empty() {
            self.dim = embedding.len();
        }
        match self.index.get(&id) {
            Some(&i) => {
                let dim = self.dim;
                self.rows[i * dim..(i + 1) * dim]
                    .iter_mut()
                    .zip(unit)
                    .for_each(|(d, v)| *d = v);
            }
            None => {
                self.index.insert(id, self.ids.len());
                self.ids.push(id);
                self.rows.extend(unit);
            }
        }
        Ok(())
    }

    /// Removes keyframe `id`; nothing happens if it is not stored.
    pub fn remove(&mut self, id: u64) {
        let Some(i) = self.index.remove(&id) else {
            return;
        };
        let last = self.ids.len() - 1;
        let dim = self.dim;
        if i != last {
            self.rows.copy_within(last * dim..(last + 1) * dim, i * dim);
            self.ids[i] = self.ids[last];
            self.index.insert(self.ids[i], i);
        }
        self.ids.pop();
        self.rows.truncate(last * dim);
    }

    /// The at most `k` stored keyframes most similar to `embedding` with cosine ≥ `min_score`,
    /// best first (equal scores by ascending id), skipping every id for which `exclude`
    /// returns true. Empty when `embedding` is zero, not finite, or not of the stored length.
    pub fn query(
        &self,
        embedding: &[f32],
        k: usize,
        min_score: f32,
        exclude: impl Fn(u64) -> bool,
    ) -> Vec<(u64, f32)> {
        if k == 0 || embedding.len() != self.dim || self.ids.is_empty() {
            return Vec::new();
        }
        let norm = embedding
            .iter()
            .map(|&v| (v as f64) * (v as f64))
            .sum::<f64>()
            .sqrt();
        if !(norm > 0.0 && norm.is_finite()) {
            return Vec::new();
        }
        let mut hits: Vec<(u64, f32)> = self
            .ids
            .iter()
            .zip(self.rows.chunks_exact(self.dim))
            .filter(|(&id, _)| !exclude(id))
            .map(|(&id, row)| {
                let dot: f64 = row
                    .iter()
                    .zip(embedding)
                    .map(|(&a, &b)| a as f64 * b as f64)
                    .sum();
                (id, (dot / norm) as f32)
            })
            .filter(|&(_, score)| score >= min_score)
            .collect();
        let order = |a: &(u64, f32), b: &(u64, f32)| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0));
        if hits.len() > k {
            hits.select_nth_unstable_by(k - 1, order);
            hits.truncate(k);
        }
        hits.sort_unstable_by(order);
        hits
    }

    /// Number of stored keyframes.
    pub fn len(&self) -> usize {
        self.ids.len()
    }

    /// Whether nothing is stored.
    pub fn is_empty(&self) -> bool {
        self.ids.is_empty()
    }

    /// Embedding length (0 while nothing was ever added).
    pub fn dim(&self) -> usize {
        self.dim
    }

    /// The stored keyframe ids, ascending.
    pub fn ids(&self) -> Vec<u64> {
        let mut ids = self.ids.clone();
        ids.sort_unstable();
        ids
    }

    /// Whether keyframe `id` is stored.
    pub fn contains(&self, id: u64) -> bool {
        self.index.contains_key(&id)
    }
}
