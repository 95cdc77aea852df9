//! Place recognition: embeddings of identical descriptor sets score 1, the binary embedding is
//! the ±1 majority vote, queries rank by cosine, honour k / min_score / exclusion, and the
//! database rejects malformed embeddings.

use dhptam_core::matching::Descriptors;
use dhptam_core::place::{embedding, PlaceDatabase};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn unit_rows(n: usize, dim: usize, r: &mut ChaCha8Rng) -> Vec<f32> {
    let mut data = Vec::with_capacity(n * dim);
    for _ in 0..n {
        let row: Vec<f32> = (0..dim).map(|_| r.random_range(-1.0f32..1.0)).collect();
        let norm = row.iter().map(|v| v * v).sum::<f32>().sqrt();
        data.extend(row.iter().map(|v| v / norm));
    }
    data
}

fn cosine(a: &[f32], b: &[f32]) -> f32 {
    let dot: f32 = a.iter().zip(b).map(|(x, y)| x * y).sum();
    let na: f32 = a.iter().map(|x| x * x).sum::<f32>().sqrt();
    let nb: f32 = b.iter().map(|x| x * x).sum::<f32>().sqrt();
    dot / (na * nb)
}

#[test]
fn float_embedding_is_the_normalised_mean() {
    let data = [1.0f32, 0.0, 0.0, 1.0, 1.0, 0.0];
    let e = embedding(Descriptors::float(&data, 2).unwrap()).unwrap();
    // Mean (2/3, 1/3) normalised: (2, 1)/√5.
    let s5 = 5f32.sqrt();
    assert!(
        (e[0] - 2.0 / s5).abs() < 1e-6 && (e[1] - 1.0 / s5).abs() < 1e-6,
        "{e:?}"
    );
    assert!(embedding(Descriptors::float(&[], 4).unwrap()).is_none());
    // Rows that cancel: a zero embedding.
    let e = embedding(Descriptors::float(&[1.0, 0.0, -1.0, 0.0], 2).unwrap()).unwrap();
    assert_eq!(e, vec![0.0, 0.0]);
}

#[test]
fn binary_embedding_is_the_bitwise_majority_vote() {
    // Two 1-byte rows: 0b0000_0101 twice and 0b0000_0011 once.
    let data = [0b0000_0101u8, 0b0000_0101, 0b0000_0011];
    let e = embedding(Descriptors::binary(&data, 1).unwrap()).unwrap();
    assert_eq!(e.len(), 8);
    // ±1 sums per bit (LSB first): bit0 +3, bit1 −1, bit2 +1, bits 3–7 −3.
    let sums = [3.0f32, -1.0, 1.0, -3.0, -3.0, -3.0, -3.0, -3.0];
    let norm = sums.iter().map(|v| v * v).sum::<f32>().sqrt();
    for (a, b) in e.iter().zip(sums) {
        assert!((a - b / norm).abs() < 1e-6, "{e:?}");
    }
    // For single rows, cosine = 1 − 2·hamming/bits.
    let mut r = ChaCha8Rng::seed_from_u64(1);
    let a: Vec<u8> = (0..32).map(|_| r.random()).collect();
    let mut b = a.clone();
    b[0] ^= 0b1111; // 4 bits flipped
    b[7] ^= 0b1000_0001; // 2 more
    let ea = embedding(Descriptors::binary(&a, 32).unwrap()).unwrap();
    let eb = embedding(Descriptors::binary(&b, 32).unwrap()).unwrap();
    assert!((cosine(&ea, &eb) - (1.0 - 2.0 * 6.0 / 256.0)).abs() < 1e-6);
}

#[test]
fn identical_sets_score_one_and_rank_first() {
    let mut r = ChaCha8Rng::seed_from_u64(2);
    let mut db = PlaceDatabase::new();
    let places: Vec<Vec<f32>> = (0..20).map(|_| unit_rows(300, 64, &mut r)).collect();
    for (id, rows) in places.iter().enumerate() {
        let e = embedding(Descriptors::float(rows, 64).unwrap()).unwrap();
        db.add(id as u64 * 10, e).unwrap();
    }
    assert_eq!(db.len(), 20);
    // The same descriptors in another order: the same place, score 1.
    let mut shuffled: Vec<&[f32]> = places[7].chunks_exact(64).collect();
    shuffled.reverse();
    let flat: Vec<f32> = shuffled.concat();
    let q = embedding(Descriptors::float(&flat, 64).unwrap()).unwrap();
    let hits = db.query(&q, 5, -1.0, |_| false);
    assert_eq!(hits.len(), 5);
    assert_eq!(hits[0].0, 70);
    assert!((hits[0].1 - 1.0).abs() < 1e-5, "{hits:?}");
    assert!(hits.windows(2).all(|w| w[0].1 >= w[1].1));
    // A revisit sharing 70 % of the descriptors still ranks first, well above the others.
    let mut revisit = places[3][..210 * 64].to_vec();
    revisit.extend(unit_rows(90, 64, &mut r));
    let q = embedding(Descriptors::float(&revisit, 64).unwrap()).unwrap();
    let hits = db.query(&q, 3, -1.0, |_| false);
    assert_eq!(hits[0].0, 30);
    assert!(hits[0].1 > 0.6 && hits[1].1 < 0.4, "{hits:?}");
}

#[test]
fn exclusion_min_score_k_and_remove() {
    let mut db = PlaceDatabase::new();
    db.add(1, vec![1.0, 0.0, 0.0]).unwrap();
    db.add(2, vec![0.9, 0.1, 0.0]).unwrap();
    db.add(3, vec![0.0, 1.0, 0.0]).unwrap();
    db.add(4, vec![-1.0, 0.0, 0.0]).unwrap();
    let q = [2.0f32, 0.0, 0.0]; // not unit: cosine still
    let ids = |h: Vec<(u64, f32)>| h.into_iter().map(|(i, _)| i).collect::<Vec<_>>();
    assert_eq!(ids(db.query(&q, 10, -1.0, |_| false)), vec![1, 2, 3, 4]);
    assert_eq!(ids(db.query(&q, 10, -1.0, |id| id == 1)), vec![2, 3, 4]);
    assert_eq!(ids(db.query(&q, 10, -1.0, |id| id % 2 == 0)), vec![1, 3]);
    assert_eq!(ids(db.query(&q, 10, 0.5, |_| false)), vec![1, 2]);
    assert_eq!(ids(db.query(&q, 1, -1.0, |_| false)), vec![1]);
    let top = db.query(&q, 1, -1.0, |_| false);
    assert!((top[0].1 - 1.0).abs() < 1e-6);
    assert!(db.query(&q, 0, -1.0, |_| false).is_empty());
    assert!(db.query(&[1.0, 0.0], 5, -1.0, |_| false).is_empty());
    assert!(db.query(&[0.0, 0.0, 0.0], 5, -1.0, |_| false).is_empty());
    // Replace, then remove: the survivors keep their embeddings.
    db.add(1, vec![0.0, 0.0, 1.0]).unwrap();
    assert_eq!(db.len(), 4);
    assert_eq!(ids(db.query(&q, 1, -1.0, |_| false)), vec![2]);
    db.remove(2);
    db.remove(99);
    assert_eq!(db.len(), 3);
    assert!(!db.contains(2));
    assert_eq!(ids(db.query(&[0.0, 1.0, 0.0], 1, -1.0, |_| false)), vec![3]);
    assert_eq!(ids(db.query(&[0.0, 0.0, 1.0], 1, -1.0, |_| false)), vec![1]);
    assert_eq!(
        ids(db.query(&[-1.0, 0.0, 0.0], 1, -1.0, |_| false)),
        vec![4]
    );
}

#[test]
fn malformed_embeddings_are_rejected() {
    let mut db = PlaceDatabase::new();
    assert!(db.add(1, vec![]).is_err());
    assert!(db
        .add(1, vec![0.0, 0.0])
        .unwrap_err()
        .to_string()
        .contains("non-zero"));
    let err = db.add(1, vec![1.0, f32::NAN]).unwrap_err();
    assert!(err.to_string().contains("embedding[1]"), "{err}");
    db.add(1, vec![1.0, 0.0]).unwrap();
    let err = db.add(2, vec![1.0, 0.0, 0.0]).unwrap_err();
    assert!(err.to_string().contains("2 values"), "{err}");
    assert_eq!(db.len(), 1);
    assert_eq!(db.dim(), 2);
}
