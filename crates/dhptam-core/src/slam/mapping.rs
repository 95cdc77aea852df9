//! Local mapping: bundle adjustment of a sliding window of covisible keyframes (older
//! observers held fixed), removal of outlier observations, and culling of points that too few
//! keyframes observe.

use std::collections::{BTreeMap, BTreeSet};
use std::sync::atomic::AtomicBool;
use std::sync::RwLock;

use nalgebra::{Vector2, Vector3};

use super::map::Map;
use super::{read_lock, write_lock, StereoCalibration};
use crate::config::{MappingConfig, TrackingConfig, TriangulationConfig};
use crate::error::Result;
use crate::solver::{
    solve_stereo_ba, BaKeyframe, BaObservation, LmOptions, Loss, StereoBaOptions, Termination,
};

/// What one local-mapping step did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct MappingReport {
    /// Keyframes optimised.
    pub optimised: usize,
    /// Keyframes held fixed.
    pub fixed: usize,
    /// Points optimised.
    pub points: usize,
    /// Observations removed as outliers.
    pub outliers_removed: usize,
    /// Points culled.
    pub culled: usize,
    /// Whether the bundle adjustment was interrupted by a newer keyframe.
    pub interrupted: bool,
}

/// Runs local bundle adjustment and culling after keyframe `kf` was inserted.
pub fn local_mapping(
    map: &RwLock<Map>,
    kf: u64,
    calib: &StereoCalibration,
    cfg: &MappingConfig,
    tracking: &TrackingConfig,
    tri: &TriangulationConfig,
    stop: Option<&AtomicBool>,
) -> Result<MappingReport> {
    let mut report = MappingReport::default();
    // 1. Gather the window under a read lock.
    let (kf_ids, mut kfs, point_ids, mut points, observations, epoch) = {
        let m = read_lock(map);
        let Some(k) = m.keyframes.get(&kf) else {
            return Ok(report);
        };
        let mut local: Vec<u64> = vec![kf];
        local.extend(k.best_covisible(cfg.window.saturating_sub(1) as usize));
        let local_set: BTreeSet<u64> = local.iter().copied().collect();
        let point_ids = m.points_of(&local);
        let mut fixed_count: BTreeMap<u64, usize> = BTreeMap::new();
        for p in &point_ids {
            for o in m.points[p].observations.keys() {
                if !local_set.contains(o) {
                    *fixed_count.entry(*o).or_insert(0) += 1;
                }
            }
        }
        let mut fixed: Vec<(u64, usize)> = fixed_count.into_iter().collect();
        fixed.sort_by(|a, b| b.1.cmp(&a.1).then(b.0.cmp(&a.0)));
        fixed.truncate(cfg.max_fixed as usize);
        let mut kf_ids: Vec<u64> = local.clone();
        kf_ids.extend(fixed.iter().map(|f| f.0));
        let mut kfs: Vec<BaKeyframe> = kf_ids
            .iter()
            .map(|id| BaKeyframe {
                cam_from_world: m.keyframes[id].world_from_cam.inverse(),
                fixed: !local_set.contains(id),
            })
            .collect();
        if fixed.is_empty() {
            // No older observer: hold the oldest window keyframe to fix the gauge.
            let oldest = (0..kf_ids.len()).min_by_key(|&i| kf_ids[i]).unwrap_or(0);
            kfs[oldest].fixed = true;
        }
        let kf_index: BTreeMap<u64, usize> =
            kf_ids.iter().enumerate().map(|(i, &id)| (id, i)).collect();
        let points: Vec<Vector3<f64>> = point_ids.iter().map(|p| m.points[p].position).collect();
        let mut observations = Vec::new();
        for (pi, p) in point_ids.iter().enumerate() {
            for (o, &feature) in &m.points[p].observations {
                let Some(&ki) = kf_index.get(o) else {
                    continue;
                };
                let k = &m.keyframes[o];
                let kp = k.keypoints[feature as usize];
                let ur = k.u_right[feature as usize];
                observations.push(BaObservation {
                    keyframe: ki,
                    point: pi,
                    pixel: Vector2::new(kp[0] as f64, kp[1] as f64),
                    u_right: ur.is_finite().then_some(ur as f64),
                });
            }
        }
        (kf_ids, kfs, point_ids, points, observations, m.corrections)
    };
    report.fixed = kfs.iter().filter(|k| k.fixed).count();
    report.optimised = kfs.len() - report.fixed;
    report.points = points.len();
    if observations.is_empty() || report.optimised == 0 {
        return Ok(report);
    }
    // 2. Solve without holding the lock.
    let options = StereoBaOptions {
        loss: Loss::Huber(tracking.huber_px),
        min_depth: tri.min_depth_m.max(1e-6),
        outlier_threshold_sq: tracking.huber_px * tracking.huber_px,
        threads: 1,
        lm: LmOptions {
            max_iterations: cfg.ba_iterations as usize,
            ..Default::default()
        },
    };
    let result = solve_stereo_ba(
        &calib.intrinsics(),
        &mut kfs,
        &mut points,
        &observations,
        &options,
        stop,
    )?;
    report.interrupted = result.report.termination == Termination::Interrupted;
    // 3. Write back under the write lock (keyframes or points removed meanwhile are skipped).
    let mut m = write_lock(map);
    if m.corrections != epoch {
        log::info!("mapping: keyframe {kf}: a loop correction intervened; result discarded");
        return Ok(report);
    }
    for (id, k) in kf_ids.iter().zip(&kfs) {
        if !k.fixed {
            if let Some(kf) = m.keyframes.get_mut(id) {
                kf.world_from_cam = k.cam_from_world.inverse();
            }
        }
    }
    for (id, x) in point_ids.iter().zip(&points) {
        if let Some(p) = m.points.get_mut(id) {
            p.position = *x;
        }
    }
    for (o, ok) in observations.iter().zip(&result.inliers) {
        if !ok {
            m.remove_observation(kf_ids[o.keyframe], point_ids[o.point]);
            report.outliers_removed += 1;
        }
    }
    // 4. Cull points observed by too few keyframes once they had the chance to be seen.
    for id in &point_ids {
        let Some(p) = m.points.get(id) else {
            continue;
        };
        let old = kf.saturating_sub(p.first_keyframe) >= cfg.cull_after_keyframes as u64;
        if p.observations.is_empty() || (old && p.observations.len() < cfg.min_observers as usize) {
            m.remove_point(*id);
            report.culled += 1;
        } else {
            m.update_normal(*id);
        }
    }
    log::debug!("mapping: keyframe {kf}: {report:?}");
    Ok(report)
}
