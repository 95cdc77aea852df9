use dhptam_core::io::{BalProblem, PoseGraph};
use dhptam_core::solver::*;
fn main() {
    let args: Vec<String> = std::env::args().collect();
    let threads: usize = args[2].parse().unwrap();
    let path = &args[1];
    if path.ends_with(".txt") {
        let mut p = BalProblem::read(path).unwrap();
        for ls in [LinearSolver::Dense, LinearSolver::Sparse] {
            let mut q = p.clone();
            let opts = BundleOptions {
                threads,
                linear_solver: ls,
                zero_behind_camera: std::env::var("ZB").is_ok(),
                ..Default::default()
            };
            let t = std::time::Instant::now();
            let r = solve_bal(&mut q, &opts).unwrap();
            println!(
                "{ls:?} {:?} {:.3}s init {:.6e} final {:.6e} it {} {:?}",
                t.elapsed(),
                r.seconds,
                r.initial_cost,
                r.final_cost,
                r.iterations,
                r.termination
            );
            println!(
                "{:?}",
                r.history
                    .iter()
                    .map(|(c, s)| format!("{c:.6e}@{s:.3}"))
                    .collect::<Vec<_>>()
            );
        }
        let _ = &mut p;
    } else {
        let g = PoseGraph::read(path).unwrap();
        let opts = PoseGraphOptions {
            threads,
            ..Default::default()
        };
        let r = match g {
            PoseGraph::Se3(mut g) => solve_pose_graph3(&mut g, &opts).unwrap(),
            PoseGraph::Se2(mut g) => solve_pose_graph2(&mut g, &opts).unwrap(),
        };
        println!(
            "{:.3}s init {:.6e} final {:.6e} it {} {:?}",
            r.seconds, r.initial_cost, r.final_cost, r.iterations, r.termination
        );
        println!(
            "{:?}",
            r.history
                .iter()
                .map(|(c, s)| format!("{c:.6e}@{s:.3}"))
                .collect::<Vec<_>>()
        );
    }
}
