//! Local mapping: fusion of duplicate map points and re-finding of points in neighbouring
//! keyframes ([`fuse_and_refind`]), bundle adjustment of a sliding window of covisible
//! keyframes (older observers held fixed), removal of outlier observations, and culling of
//! points that too few keyframes observe. Each step can be interrupted by a newer keyframe.

use std::collections::{BTreeMap, BTreeSet};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Mutex, RwLock};

use nalgebra::{Vector2, Vector3};
use rayon::prelude::*;

use super::map::Map;
use super::tracking::{Grid, Projection};
use super::{read_lock, write_lock, StereoCalibration};
use crate::config::{MappingConfig, TrackingConfig, TriangulationConfig};
use crate::error::Result;
use crate::place::PlaceDatabase;
use crate::solver::{
    solve_stereo_ba, BaKeyframe, BaObservation, CentrePrior, LmOptions, Loss, StereoBaOptions,
    Termination,
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
    /// Points culled (too few observers, or rarely found when predicted visible).
    pub culled: usize,
    /// Of `culled`: points removed because the window's keyframes rarely observe them where
    /// they project into their view ([`MappingConfig::min_found_ratio`]).
    pub culled_unfound: usize,
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
    // 1. The window: `kf`, its best covisible keyframes, and the older keyframes observing
    // most of their points, held fixed; the points of the window.
    let select = |m: &Map| -> Option<Selection> {
        let k = m.keyframes.get(&kf)?;
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
        // Without an older observer the oldest window keyframe is held to fix the gauge.
        let anchor = fixed
            .is_empty()
            .then(|| local.iter().copied().min())
            .flatten();
        let mut keyframes: Vec<(u64, bool)> =
            local.iter().map(|&id| (id, Some(id) == anchor)).collect();
        keyframes.extend(fixed.iter().map(|f| (f.0, true)));
        Some(Selection {
            keyframes,
            point_ids,
            prior: PriorRule::of(cfg),
        })
    };
    // 2. Bundle adjustment of the window, outlier observations removed.
    let Some(adjusted) = adjust(
        map,
        select,
        calib,
        tracking,
        tri,
        cfg.ba_iterations,
        stop,
        &format!("keyframe {kf}"),
    )?
    else {
        return Ok(MappingReport::default());
    };
    let Adjusted {
        mut report,
        window,
        point_ids,
        mut m,
    } = adjusted;
    // 3. Cull points observed by too few keyframes once they had the chance to be seen, and
    // points the window's keyframes rarely find where they predict them.
    for id in &point_ids {
        let Some(p) = m.points.get(id) else {
            continue;
        };
        let old = kf.saturating_sub(p.first_keyframe) >= cfg.cull_after_keyframes as u64;
        let unfound = old && rarely_found(&m, *id, &window, calib, tracking, tri, cfg);
        if p.observations.is_empty()
            || (old && p.observations.len() < cfg.min_observers as usize)
            || unfound
        {
            m.remove_point(*id);
            report.culled += 1;
            report.culled_unfound += unfound as usize;
        } else {
            m.update_normal(*id);
        }
    }
    m.prune_replaced(replaced_horizon(cfg));
    log::debug!("mapping: keyframe {kf}: {report:?}");
    Ok(report)
}

/// Bundle adjustment of the whole map: every keyframe and every point, the first keyframe of
/// the map and of each map segment not joined to it yet held fixed (one gauge per segment),
/// `iterations` Levenberg–Marquardt iterations (the local windows' Huber loss and outlier
/// bound); outlier observations are removed, and points left without any observation with
/// them. After the last frame of a run ([`super::System::refine_map`]) it spreads what loop
/// closing's pose graph and the local windows could not: every observation of every point
/// weighs on every keyframe at once.
pub fn global_bundle_adjustment(
    map: &RwLock<Map>,
    calib: &StereoCalibration,
    tracking: &TrackingConfig,
    tri: &TriangulationConfig,
    iterations: u32,
    stop: Option<&AtomicBool>,
) -> Result<MappingReport> {
    // Every keyframe (the first of the map and of each unjoined segment held), their points.
    let select = |m: &Map| -> Option<Selection> {
        let first = m.keyframes.keys().next().copied();
        Some(Selection {
            keyframes: m
                .keyframes
                .keys()
                .map(|&id| (id, Some(id) == first || m.segment_starts.contains(&id)))
                .collect(),
            point_ids: m.points_of(&m.keyframes.keys().copied().collect::<Vec<u64>>()),
            prior: PriorRule::NONE,
        })
    };
    let Some(Adjusted {
        mut report,
        point_ids,
        mut m,
        ..
    }) = adjust(
        map,
        select,
        calib,
        tracking,
        tri,
        iterations,
        stop,
        "whole map",
    )?
    else {
        return Ok(MappingReport::default());
    };
    for id in &point_ids {
        match m.points.get(id) {
            Some(p) if p.observations.is_empty() => {
                m.remove_point(*id);
                report.culled += 1;
            }
            Some(_) => m.update_normal(*id),
            None => {}
        }
    }
    log::info!(
        "mapping: whole-map bundle adjustment: {} keyframes ({} fixed), {} points, {} outlier observations removed",
        report.optimised + report.fixed,
        report.fixed,
        report.points,
        report.outliers_removed
    );
    Ok(report)
}

/// The problem [`adjust`] solves, chosen under its read lock: keyframes (id, held fixed)
/// and points; every observation of those points by those keyframes enters.
struct Selection {
    keyframes: Vec<(u64, bool)>,
    point_ids: Vec<u64>,
    /// Which free keyframes get a centre prior, and how wide.
    prior: PriorRule,
}

/// `[mapping] centre_prior_scale` and `centre_prior_below`: free keyframes with fewer than
/// `below` map points shared with another keyframe get a centre prior `scale` times as wide
/// as their tracking deviation (`scale` 0: none).
#[derive(Clone, Copy)]
struct PriorRule {
    scale: f64,
    below: usize,
}

impl PriorRule {
    const NONE: Self = Self {
        scale: 0.0,
        below: 0,
    };

    fn of(cfg: &MappingConfig) -> Self {
        Self {
            scale: cfg.centre_prior_scale,
            below: cfg.centre_prior_below as usize,
        }
    }
}

/// How many of keyframe `k`'s map points another keyframe observes too: what ties it to the
/// rest of the map.
fn shared_points(m: &Map, k: &super::map::Keyframe) -> usize {
    k.points
        .iter()
        .flatten()
        .filter(|p| m.points.get(p).is_some_and(|p| p.observations.len() > 1))
        .count()
}

/// What [`adjust`] leaves to its caller: the report so far, the keyframes it optimised, the
/// points of the problem, and the map, still write-locked, with the result written back.
struct Adjusted<'a> {
    report: MappingReport,
    window: Vec<u64>,
    point_ids: Vec<u64>,
    m: std::sync::RwLockWriteGuard<'a, Map>,
}

/// Stereo bundle adjustment of the problem `select` chooses from the map: gathered under a
/// read lock, solved without a lock, written back under the write lock (keyframes and points
/// removed meanwhile skipped) with the outlier observations removed. `None` when `select`
/// finds nothing, there is nothing to optimise, or a loop correction intervened (the result
/// is then discarded, logged with `what`).
#[allow(clippy::too_many_arguments)]
fn adjust<'a>(
    map: &'a RwLock<Map>,
    select: impl FnOnce(&Map) -> Option<Selection>,
    calib: &StereoCalibration,
    tracking: &TrackingConfig,
    tri: &TriangulationConfig,
    iterations: u32,
    stop: Option<&AtomicBool>,
    what: &str,
) -> Result<Option<Adjusted<'a>>> {
    let mut report = MappingReport::default();
    let (kf_ids, mut kfs, point_ids, mut points, observations, epoch) = {
        let m = read_lock(map);
        let Some(Selection {
            keyframes,
            point_ids,
            prior,
        }) = select(&m)
        else {
            return Ok(None);
        };
        let kf_ids: Vec<u64> = keyframes.iter().map(|(id, _)| *id).collect();
        let kfs: Vec<BaKeyframe> = keyframes
            .iter()
            .map(|(id, held)| {
                let k = &m.keyframes[id];
                let prior = (!*held && prior.scale > 0.0 && shared_points(&m, k) < prior.below)
                    .then(|| centre_prior(&m, k, prior.scale))
                    .flatten();
                BaKeyframe {
                    cam_from_world: k.world_from_cam.inverse(),
                    fixed: *held,
                    prior,
                }
            })
            .collect();
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
                    viewpoint: k.viewpoints[feature as usize].map(f64::from).into(),
                    sigma: k.sigmas[feature as usize] as f64,
                });
            }
        }
        (kf_ids, kfs, point_ids, points, observations, m.corrections)
    };
    report.fixed = kfs.iter().filter(|k| k.fixed).count();
    report.optimised = kfs.len() - report.fixed;
    report.points = points.len();
    if observations.is_empty() || report.optimised == 0 {
        return Ok(None);
    }
    let options = StereoBaOptions {
        loss: Loss::Huber(tracking.huber_px),
        min_depth: tri.min_depth_m.max(1e-6),
        outlier_threshold_sq: tracking.huber_px * tracking.huber_px,
        threads: 1,
        lm: LmOptions {
            max_iterations: iterations as usize,
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
    let mut m = write_lock(map);
    if m.corrections != epoch {
        log::info!("mapping: {what}: a loop correction intervened; result discarded");
        return Ok(None);
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
    let window = kf_ids
        .iter()
        .zip(&kfs)
        .filter(|(_, k)| !k.fixed)
        .map(|(id, _)| *id)
        .collect();
    Ok(Some(Adjusted {
        report,
        window,
        point_ids,
        m,
    }))
}

/// The prior on keyframe `k`'s centre for `[mapping] centre_prior_scale` = `scale`: at its
/// centre now, with the position covariance the tracker measured for the frame that became
/// it (in the camera's axes, turned into the world's) times `scale²`. `None` when that frame
/// has no measured covariance or it is not invertible.
fn centre_prior(m: &Map, k: &super::map::Keyframe, scale: f64) -> Option<CentrePrior> {
    let at = m.trajectory.partition_point(|r| r.t_ns < k.t_ns);
    let record = m.trajectory.get(at).filter(|r| r.t_ns == k.t_ns)?;
    let information_cam = (record.position_cov? * (scale * scale)).try_inverse()?;
    let r = k.world_from_cam.rotation.matrix();
    let information = r * information_cam * r.transpose();
    information
        .iter()
        .all(|x| x.is_finite())
        .then_some(CentrePrior {
            centre: k.centre(),
            information,
        })
}

/// How many keyframes back [`Map::replaced`] entries are kept: a reader holds point ids for
/// one tracking or mapping step, during which at most `queue + 2` keyframes can be inserted;
/// four times that, and at least [`REPLACED_HORIZON_MIN`], leaves a wide margin.
pub fn replaced_horizon(cfg: &MappingConfig) -> u64 {
    REPLACED_HORIZON_MIN.max(4 * (cfg.queue as u64 + 2))
}

/// Smallest [`replaced_horizon`], keyframes.
pub const REPLACED_HORIZON_MIN: u64 = 64;

/// Whether the keyframes `window` observe point `id` in less than
/// [`MappingConfig::min_found_ratio`] of those whose view it projects into (inside the image,
/// within the depth limits and the viewing-angle limit of tracking), counting only when at
/// least [`MIN_PREDICTIONS`] keyframes predict it. Keyframes that observe the point count as
/// predicting it.
fn rarely_found(
    map: &Map,
    id: u64,
    window: &[u64],
    calib: &StereoCalibration,
    tracking: &TrackingConfig,
    tri: &TriangulationConfig,
    cfg: &MappingConfig,
) -> bool {
    if cfg.min_found_ratio <= 0.0 {
        return false;
    }
    let Some(p) = map.points.get(&id) else {
        return false;
    };
    let cos_max = tracking.max_view_angle_deg.to_radians().cos();
    let (w, h) = (calib.width as f64, calib.height as f64);
    let (mut predicted, mut found) = (0usize, 0usize);
    for k in window.iter().filter_map(|k| map.keyframes.get(k)) {
        if p.observations.contains_key(&k.id) {
            predicted += 1;
            found += 1;
            continue;
        }
        let pc = k.world_from_cam.inverse().transform_point(&p.position);
        if pc.z < tri.min_depth_m || pc.z > tri.max_depth_m {
            continue;
        }
        let u = calib.fx * pc.x / pc.z + calib.cx;
        let v = calib.fy * pc.y / pc.z + calib.cy;
        let ray = p.position - k.centre();
        if u >= 0.0 && v >= 0.0 && u < w && v < h && ray.dot(&p.normal) >= cos_max * ray.norm() {
            predicted += 1;
        }
    }
    predicted >= MIN_PREDICTIONS && (found as f64) < cfg.min_found_ratio * predicted as f64
}

/// Keyframes that must predict a point before its found ratio can condemn it.
pub const MIN_PREDICTIONS: usize = 3;

// --- keyframe culling (issue 10) ---
/// What one keyframe-culling step did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct CullReport {
    /// Keyframes examined.
    pub examined: usize,
    /// Keyframes removed as redundant (ids).
    pub removed: Vec<u64>,
}

/// The fraction of keyframe `id`'s map points that at least
/// [`MappingConfig::redundant_observers`] other keyframes observe at the same or a finer scale
/// (from no farther than [`MappingConfig::redundant_distance_ratio`] times `id`'s own distance
/// to the point) and from a similar direction (their ray to the point within
/// [`MappingConfig::redundant_max_angle_deg`] of `id`'s); `None` for a keyframe without points.
pub fn redundancy(map: &Map, id: u64, cfg: &MappingConfig) -> Option<f64> {
    let k = map.keyframes.get(&id)?;
    let centre = k.centre();
    let cos_max = cfg.redundant_max_angle_deg.to_radians().cos();
    let (mut total, mut redundant) = (0usize, 0usize);
    for pid in k.points.iter().flatten() {
        let Some(p) = map.points.get(pid) else {
            continue;
        };
        total += 1;
        let own = p.position - centre;
        let own_norm = own.norm();
        let reach = cfg.redundant_distance_ratio * own_norm;
        let others = p
            .observations
            .keys()
            .filter(|&&o| o != id)
            .filter_map(|o| map.keyframes.get(o))
            .filter(|o| {
                let ray = p.position - o.centre();
                let n = ray.norm();
                n <= reach && ray.dot(&own) >= cos_max * n * own_norm
            })
            .count();
        if others >= cfg.redundant_observers as usize {
            redundant += 1;
        }
    }
    (total > 0).then(|| redundant as f64 / total as f64)
}

/// The keyframes at the place of keyframe `kf`, `kf` included: camera centres within
/// [`MappingConfig::place_radius_ratio`] times `kf`'s median point depth of `kf`'s centre and
/// optical axes within [`MappingConfig::place_max_angle_deg`] of `kf`'s. Empty when `kf` is
/// missing or observes no point in front of it.
pub fn keyframes_at_place(map: &Map, kf: u64, cfg: &MappingConfig) -> Vec<u64> {
    let Some(k) = map.keyframes.get(&kf) else {
        return Vec::new();
    };
    let cam_from_world = k.world_from_cam.inverse();
    let mut depths: Vec<f64> = k
        .points
        .iter()
        .flatten()
        .filter_map(|p| map.points.get(p))
        .map(|p| cam_from_world.transform_point(&p.position).z)
        .filter(|z| *z > 0.0)
        .collect();
    if depths.is_empty() {
        return Vec::new();
    }
    depths.sort_by(f64::total_cmp);
    let radius = cfg.place_radius_ratio * depths[depths.len() / 2];
    let axis = |s: &super::map::Keyframe| s.world_from_cam.rotation * Vector3::z();
    let own_axis = axis(k);
    let cos_max = cfg.place_max_angle_deg.to_radians().cos();
    let centre = k.centre();
    map.keyframes
        .values()
        .filter(|o| (o.centre() - centre).norm() <= radius && axis(o).dot(&own_axis) >= cos_max)
        .map(|o| o.id)
        .collect()
}

/// Whether removing keyframe `c` leaves each keyframe covisible with it at least
/// `min(cull_keep_shared, what it has now)` map points that some keyframe other than itself
/// and `c` observes too ([`MappingConfig::cull_keep_shared`]).
fn neighbours_stay_tied(map: &Map, c: u64, cfg: &MappingConfig) -> bool {
    let Some(k) = map.keyframes.get(&c) else {
        return false;
    };
    let floor = cfg.cull_keep_shared as usize;
    k.covisible.keys().all(|n| {
        let Some(nk) = map.keyframes.get(n) else {
            return true;
        };
        let (mut before, mut after) = (0usize, 0usize);
        for p in nk.points.iter().flatten().filter_map(|p| map.points.get(p)) {
            let others = p.observations.len().saturating_sub(1);
            if others >= 1 {
                before += 1;
                if others - usize::from(p.observations.contains_key(&c)) >= 1 {
                    after += 1;
                }
            }
        }
        after >= before.min(floor)
    })
}

/// Removes redundant keyframes after keyframe `kf` was mapped, so that the map holds at most
/// [`MappingConfig::keyframes_per_place`] keyframes at `kf`'s place ([`keyframes_at_place`])
/// and at the place of the keyframe that has just become old enough to be culled (the newest
/// at least [`MappingConfig::cull_min_age`] keyframes older than `kf`: a keyframe that
/// duplicates older ones goes as soon as it leaves the active window, not only when the
/// camera comes back once more). With a budget of 0, every redundant keyframe covisible with
/// `kf` is a candidate, wherever it is.
///
/// A candidate is removed, most redundant first (ties: the newer), at most
/// [`MappingConfig::cull_max_per_keyframe`] per call, when all of these hold:
/// - at least [`MappingConfig::redundant_fraction`] of its points are seen by enough other
///   keyframes at the same or a finer scale and from a similar direction ([`redundancy`],
///   re-evaluated against the map as the previous removals left it);
/// - it is at least [`MappingConfig::cull_min_age`] keyframes older than `kf` and not in
///   `kf`'s local bundle-adjustment window (`kf` and its `window − 1` most covisible
///   keyframes), so the constraints tracking and mapping work with right now stay;
/// - it is not the map's first keyframe, a keyframe of an accepted loop or the first keyframe
///   of a map segment;
/// - each keyframe covisible with it keeps enough points shared with the rest of the map
///   ([`MappingConfig::cull_keep_shared`]).
///
/// A removed keyframe's observations, trajectory records and covisibility are handed over by
/// [`Map::cull_keyframe`] (records to its most covisible keyframe) and its place-database entry
/// is removed under the same map lock.
pub fn cull_keyframes(
    map: &RwLock<Map>,
    place: &Mutex<PlaceDatabase>,
    kf: u64,
    cfg: &MappingConfig,
) -> CullReport {
    let mut report = CullReport::default();
    if !cfg.cull_keyframes {
        return report;
    }
    let mut m = write_lock(map);
    let Some(k) = m.keyframes.get(&kf) else {
        return report;
    };
    let first = m.keyframes.keys().next().copied();
    let window = k.best_covisible(cfg.window.saturating_sub(1) as usize);
    let protected: BTreeSet<u64> = m
        .loops
        .iter()
        .flat_map(|&(a, b)| [a, b])
        .chain(m.segment_starts.iter().copied())
        .chain(first)
        .chain(window)
        .collect();
    let eligible = |c: u64| {
        c < kf && c.saturating_add(cfg.cull_min_age as u64) <= kf && !protected.contains(&c)
    };
    if cfg.keyframes_per_place == 0 {
        let pool: Vec<u64> = k.covisible.keys().copied().collect();
        cull_among(
            &mut m,
            place,
            kf,
            pool,
            usize::MAX,
            &eligible,
            cfg,
            &mut report,
        );
        return report;
    }
    let aged = m
        .keyframes
        .range(..=kf.saturating_sub(cfg.cull_min_age as u64))
        .next_back()
        .map(|(&id, _)| id)
        .filter(|&a| a != kf);
    for anchor in std::iter::once(kf).chain(aged) {
        let here = keyframes_at_place(&m, anchor, cfg);
        let crowd = here.len();
        cull_among(&mut m, place, kf, here, crowd, &eligible, cfg, &mut report);
    }
    report
}

/// Removes the most redundant eligible keyframes of `pool` (see [`cull_keyframes`]) while
/// more than [`MappingConfig::keyframes_per_place`] of `crowd` remain and the per-call cap is
/// not reached.
#[allow(clippy::too_many_arguments)]
fn cull_among(
    m: &mut Map,
    place: &Mutex<PlaceDatabase>,
    kf: u64,
    pool: Vec<u64>,
    mut crowd: usize,
    eligible: &dyn Fn(u64) -> bool,
    cfg: &MappingConfig,
    report: &mut CullReport,
) {
    let budget = cfg.keyframes_per_place as usize;
    let cap = cfg.cull_max_per_keyframe as usize;
    if crowd <= budget || report.removed.len() >= cap {
        return;
    }
    let mut ranked: Vec<(f64, u64)> = pool
        .into_iter()
        .filter(|&c| eligible(c))
        .filter_map(|c| {
            report.examined += 1;
            redundancy(m, c, cfg)
                .filter(|&r| r >= cfg.redundant_fraction)
                .map(|r| (r, c))
        })
        .collect();
    ranked.sort_by(|a, b| b.0.total_cmp(&a.0).then(b.1.cmp(&a.1)));
    for (_, c) in ranked {
        if report.removed.len() >= cap || crowd <= budget {
            break;
        }
        // Earlier removals this step may have made `c` the only observer of some points.
        let Some(r) = redundancy(m, c, cfg).filter(|&r| r >= cfg.redundant_fraction) else {
            continue;
        };
        if !neighbours_stay_tied(m, c, cfg) {
            continue;
        }
        let Some(substitute) = m
            .keyframes
            .get(&c)
            .and_then(|k| k.best_covisible(1).first().copied())
        else {
            continue;
        };
        if m.cull_keyframe(c, substitute) {
            super::lock(place).remove(c);
            log::debug!(
                "mapping: keyframe {kf}: keyframe {c} culled ({:.0} % of its points redundant, \
                 {crowd} keyframes at the place; its frames now refer to keyframe {substitute})",
                100.0 * r
            );
            report.removed.push(c);
            crowd = crowd.saturating_sub(1);
        }
    }
}

// --- end keyframe culling ---

/// What one fusion step did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct FusionReport {
    /// Neighbour keyframes searched.
    pub neighbours: usize,
    /// Duplicate points fused into others.
    pub merged: usize,
    /// Observations added to points re-found in keyframes that did not observe them.
    pub refound: usize,
    /// Whether the search was interrupted by a newer keyframe (what was found until then is
    /// applied).
    pub interrupted: bool,
}

/// A projection of a map point matched to a keypoint of a keyframe.
#[derive(Clone, Copy, Debug)]
struct Proposal {
    keyframe: u64,
    feature: usize,
    point: u64,
    distance: f32,
}

/// Projects `points` into keyframe `target` and matches each to the keypoints within
/// `cfg.fuse_radius_px` of its projection (and of its predicted right column for stereo
/// keypoints), by descriptor distance and ratio test. Points `target` already observes are
/// skipped.
#[allow(clippy::too_many_arguments)]
fn project_into(
    map: &Map,
    target: u64,
    points: &[u64],
    calib: &StereoCalibration,
    cfg: &MappingConfig,
    tracking: &TrackingConfig,
    tri: &TriangulationConfig,
) -> Vec<Proposal> {
    let Some(t) = map.keyframes.get(&target) else {
        return Vec::new();
    };
    let descriptors = t.descriptors.view();
    let grid = Grid::new(
        &t.keypoints,
        calib.width,
        calib.height,
        tracking.cell_px as f32,
    );
    let projection = Projection::new(
        &t.world_from_cam.inverse(),
        calib,
        tracking,
        tri,
        descriptors.kind(),
        cfg.fuse_radius_px as f32,
    )
    // One viewpoint per search: the first keypoint's (a bridge keyframe's is the image
    // tracked before the switch; its other image's keypoints are searched a few pixels off).
    .seen_from(
        t.viewpoints
            .first()
            .map_or(Vector3::zeros(), |c| c.map(f64::from).into()),
    );
    points
        .par_iter()
        .filter_map(|&id| {
            let p = map.points.get(&id)?;
            if p.observations.contains_key(&target) {
                return None;
            }
            let (feature, distance) =
                projection.best_match(p, &t.keypoints, &t.u_right, descriptors, &grid)?;
            Some(Proposal {
                keyframe: target,
                feature,
                point: id,
                distance,
            })
        })
        .collect()
}

/// Fuses duplicate map points and re-finds points around keyframe `kf` (before its local
/// bundle adjustment). The neighbours are `kf`'s `fuse_neighbours` most covisible keyframes
/// and the `fuse_temporal` keyframes before it. `kf`'s points are projected into each
/// neighbour and each neighbour's points into `kf` ([`MappingConfig::fuse_radius_px`],
/// descriptor thresholds of tracking). A projection that matches a keypoint observing another
/// point fuses the two (the point with more observations, or the older, keeps its id; the
/// other id resolves to it through [`Map::resolve`]); one that matches a free keypoint adds
/// the observation. Pairs that some keyframe observes both of are distinct and left alone.
/// The search runs under a read lock and checks `stop` between keyframes; the changes are
/// applied under the write lock, re-checked against the map as it is then (and dropped if a
/// loop correction intervened).
#[allow(clippy::too_many_arguments)]
pub fn fuse_and_refind(
    map: &RwLock<Map>,
    kf: u64,
    calib: &StereoCalibration,
    cfg: &MappingConfig,
    tracking: &TrackingConfig,
    tri: &TriangulationConfig,
    stop: Option<&AtomicBool>,
) -> Result<FusionReport> {
    let mut report = FusionReport::default();
    let (proposals, epoch) = {
        let m = read_lock(map);
        let Some(k) = m.keyframes.get(&kf) else {
            return Ok(report);
        };
        let mut neighbours: Vec<u64> = k.best_covisible(cfg.fuse_neighbours as usize);
        for (&id, _) in m
            .keyframes
            .range(..kf)
            .rev()
            .take(cfg.fuse_temporal as usize)
        {
            if !neighbours.contains(&id) {
                neighbours.push(id);
            }
        }
        report.neighbours = neighbours.len();
        let own = m.points_of(&[kf]);
        let mut proposals = Vec::new();
        let stopped = || stop.is_some_and(|s| s.load(Ordering::Acquire));
        for &n in &neighbours {
            if stopped() {
                report.interrupted = true;
                break;
            }
            proposals.extend(project_into(&m, n, &own, calib, cfg, tracking, tri));
        }
        // The neighbours' points (each once, however many neighbours observe it) into `kf`.
        if !report.interrupted && !stopped() {
            let theirs = m.points_of(&neighbours);
            proposals.extend(project_into(&m, kf, &theirs, calib, cfg, tracking, tri));
        } else {
            report.interrupted = true;
        }
        (proposals, m.corrections)
    };
    // One proposal per keypoint: the closest descriptor (ties: the lower point id).
    let mut best: BTreeMap<(u64, usize), Proposal> = BTreeMap::new();
    for p in proposals {
        match best.get(&(p.keyframe, p.feature)) {
            Some(b) if (b.distance, b.point) <= (p.distance, p.point) => {}
            _ => {
                best.insert((p.keyframe, p.feature), p);
            }
        }
    }
    let mut m = write_lock(map);
    if m.corrections != epoch {
        log::info!("mapping: keyframe {kf}: a loop correction intervened; fusion discarded");
        return Ok(report);
    }
    for p in best.into_values() {
        let point = m.resolve(p.point);
        let Some(observers) = m.points.get(&point).map(|x| x.observations.clone()) else {
            continue;
        };
        if observers.contains_key(&p.keyframe) {
            continue;
        }
        let Some(slot) = m
            .keyframes
            .get(&p.keyframe)
            .and_then(|k| k.points.get(p.feature).copied())
        else {
            continue;
        };
        match slot.map(|q| m.resolve(q)) {
            None => {
                m.add_observation(p.keyframe, p.feature, point);
                report.refound += 1;
            }
            Some(other) if other == point => {}
            Some(other) => {
                let Some(theirs) = m.points.get(&other).map(|x| x.observations.clone()) else {
                    continue;
                };
                if observers.keys().any(|k| theirs.contains_key(k)) {
                    continue;
                }
                let (keep, drop) = if (theirs.len(), std::cmp::Reverse(other))
                    >= (observers.len(), std::cmp::Reverse(point))
                {
                    (other, point)
                } else {
                    (point, other)
                };
                if m.merge_points(keep, drop) {
                    report.merged += 1;
                }
            }
        }
    }
    log::debug!("mapping: keyframe {kf}: fusion {report:?}");
    Ok(report)
}
