//! The Levenberg–Marquardt loop shared by every solver of this module.
//!
//! Each iteration solves the damped normal equations (JᵀJ + μD) δ = −Jᵀr with D the diagonal
//! of JᵀJ clamped to [`LmOptions::min_diagonal`, `LmOptions::max_diagonal`] and μ = 1/Δ for a
//! trust-region radius Δ. The gain ratio ϱ = (F(x) − F(x ⊞ δ)) / (L(0) − L(δ)) between the
//! actual and the model decrease drives Δ (Nielsen, "Damping parameter in Marquardt's method",
//! 1999): a step with ϱ above `min_relative_decrease` is taken and Δ ← Δ / max(⅓, 1 − (2ϱ − 1)³);
//! a rejected step divides Δ by ν and doubles ν. For the model L(δ) = F + gᵀδ + ½δᵀJᵀJδ and
//! a δ that solves the damped system, L(0) − L(δ) = ½ (−gᵀδ + μ δᵀDδ).
//!
//! Costs are ½Σρ(‖rᵢ‖²), the definition Ceres and GTSAM report, so figures compare directly.

use std::time::Instant;

use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};

/// Stopping rules and damping bounds of [`solve`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LmOptions {
    /// Most outer iterations (successful or not).
    pub max_iterations: usize,
    /// Stop when a successful step changes the cost by less than this fraction of it.
    pub function_tolerance: f64,
    /// Stop when the largest gradient component falls below this.
    pub gradient_tolerance: f64,
    /// Stop when ‖δ‖ ≤ tol · (‖x‖ + tol).
    pub parameter_tolerance: f64,
    /// Initial trust-region radius Δ (damping μ = 1/Δ).
    pub initial_trust_radius: f64,
    /// Largest radius Δ.
    pub max_trust_radius: f64,
    /// Stop when Δ shrinks below this: no decrease can be found.
    pub min_trust_radius: f64,
    /// Lower clamp of the damping diagonal D.
    pub min_diagonal: f64,
    /// Upper clamp of the damping diagonal D.
    pub max_diagonal: f64,
    /// Smallest gain ratio ϱ at which a step is taken.
    pub min_relative_decrease: f64,
}

impl Default for LmOptions {
    fn default() -> Self {
        Self {
            max_iterations: 50,
            function_tolerance: 1e-6,
            gradient_tolerance: 1e-10,
            parameter_tolerance: 1e-8,
            initial_trust_radius: 1e4,
            max_trust_radius: 1e16,
            min_trust_radius: 1e-32,
            min_diagonal: 1e-6,
            max_diagonal: 1e32,
            min_relative_decrease: 1e-3,
        }
    }
}

impl LmOptions {
    /// Checks the ranges, naming the offending field.
    pub fn check(&self) -> Result<()> {
        let positive = [
            ("initial_trust_radius", self.initial_trust_radius),
            ("max_trust_radius", self.max_trust_radius),
            ("min_trust_radius", self.min_trust_radius),
            ("min_diagonal", self.min_diagonal),
            ("max_diagonal", self.max_diagonal),
        ];
        for (name, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return Err(Error::invalid(name, "a positive finite number", v));
            }
        }
        let non_negative = [
            ("function_tolerance", self.function_tolerance),
            ("gradient_tolerance", self.gradient_tolerance),
            ("parameter_tolerance", self.parameter_tolerance),
            ("min_relative_decrease", self.min_relative_decrease),
        ];
        for (name, v) in non_negative {
            if !(v.is_finite() && v >= 0.0) {
                return Err(Error::invalid(name, "a non-negative finite number", v));
            }
        }
        Ok(())
    }
}

/// Why [`solve`] stopped.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Termination {
    /// The relative cost change of a step fell below `function_tolerance`.
    FunctionTolerance,
    /// The gradient fell below `gradient_tolerance`.
    GradientTolerance,
    /// The step fell below `parameter_tolerance`.
    ParameterTolerance,
    /// `max_iterations` were spent.
    MaxIterations,
    /// The trust region collapsed without finding a decrease.
    NoDecrease,
    /// The caller asked the solve to stop ([`LeastSquares::interrupted`]); the estimate is
    /// the best one reached so far.
    Interrupted,
}

impl Termination {
    /// Lower-case name for reports and JSON.
    pub fn name(&self) -> &'static str {
        match self {
            Termination::FunctionTolerance => "function_tolerance",
            Termination::GradientTolerance => "gradient_tolerance",
            Termination::ParameterTolerance => "parameter_tolerance",
            Termination::MaxIterations => "max_iterations",
            Termination::NoDecrease => "no_decrease",
            Termination::Interrupted => "interrupted",
        }
    }
}

/// What one solve did.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LmReport {
    /// ½Σρ(‖r‖²) at the start.
    pub initial_cost: f64,
    /// ½Σρ(‖r‖²) at the end.
    pub final_cost: f64,
    /// Outer iterations, successful and rejected.
    pub iterations: usize,
    /// Steps that were taken.
    pub successful_steps: usize,
    /// Wall-clock seconds of the whole solve.
    pub seconds: f64,
    /// Why the loop stopped.
    pub termination: Termination,
    /// (cost, seconds since the start) after each taken step, starting with the initial cost.
    pub history: Vec<(f64, f64)>,
}

impl LmReport {
    /// Adds the time spent preparing the problem before the loop started to `seconds` and
    /// to every history entry, so that times count from the call that built the problem.
    pub fn include_setup(&mut self, setup_seconds: f64) {
        self.seconds += setup_seconds;
        for (_, s) in &mut self.history {
            *s += setup_seconds;
        }
    }

    /// Seconds until the cost first reached `target`, `None` if it never did.
    pub fn seconds_to_cost(&self, target: f64) -> Option<f64> {
        self.history
            .iter()
            .find(|(c, _)| *c <= target)
            .map(|&(_, s)| s)
    }
}

/// The model decrease and size of a candidate step.
#[derive(Clone, Copy, Debug)]
pub struct Step {
    /// L(0) − L(δ) = ½ (−gᵀδ + μ δᵀDδ).
    pub model_decrease: f64,
    /// ‖δ‖₂.
    pub norm: f64,
}

/// A least-squares problem as the LM loop sees it. The problem keeps its current estimate,
/// a linearisation of it, and at most one candidate step.
pub trait LeastSquares {
    /// ½Σρ(‖r‖²) at the current estimate.
    fn cost(&mut self) -> f64;
    /// Evaluates residuals and Jacobians at the current estimate; returns ‖Jᵀr‖∞.
    fn linearize(&mut self) -> f64;
    /// Solves the system damped by μ·clamp(diag(JᵀJ), lo, hi) for a candidate step.
    /// `None` when the damped system could not be factorised.
    fn compute_step(&mut self, mu: f64, min_diagonal: f64, max_diagonal: f64) -> Option<Step>;
    /// ½Σρ at the candidate x ⊞ δ (non-finite when the candidate is invalid).
    fn candidate_cost(&mut self) -> f64;
    /// Makes the candidate the current estimate.
    fn accept(&mut self);
    /// ‖x‖₂ of the current estimate, for the step tolerance.
    fn state_norm(&self) -> f64;
    /// Whether the caller asked the solve to stop; checked before every iteration. Since only
    /// decreasing steps are accepted, the current estimate is then the best one so far.
    fn interrupted(&self) -> bool {
        false
    }
}

/// Runs Levenberg–Marquardt on `problem` from its current estimate.
pub fn solve<P: LeastSquares + ?Sized>(problem: &mut P, options: &LmOptions) -> Result<LmReport> {
    options.check()?;
    let start = Instant::now();
    let mut cost = problem.cost();
    if !cost.is_finite() {
        return Err(Error::numerical(
            "least squares",
            format!("the initial cost is {cost}"),
        ));
    }
    let initial_cost = cost;
    let mut history = vec![(cost, 0.0)];
    let mut radius = options.initial_trust_radius;
    let mut nu = 2.0;
    let mut iterations = 0;
    let mut successful_steps = 0;
    let mut gradient_max = problem.linearize();
    let termination = loop {
        if problem.interrupted() {
            break Termination::Interrupted;
        }
        if gradient_max <= options.gradient_tolerance {
            break Termination::GradientTolerance;
        }
        if iterations >= options.max_iterations {
            break Termination::MaxIterations;
        }
        if radius < options.min_trust_radius {
            break Termination::NoDecrease;
        }
        iterations += 1;
        let Some(step) =
            problem.compute_step(1.0 / radius, options.min_diagonal, options.max_diagonal)
        else {
            radius /= nu;
            nu *= 2.0;
            continue;
        };
        let tol = options.parameter_tolerance;
        if step.norm <= tol * (problem.state_norm() + tol) {
            break Termination::ParameterTolerance;
        }
        let new_cost = problem.candidate_cost();
        let ratio = (cost - new_cost) / step.model_decrease;
        if !(new_cost.is_finite()
            && step.model_decrease > 0.0
            && ratio > options.min_relative_decrease)
        {
            radius /= nu;
            nu *= 2.0;
            continue;
        }
        problem.accept();
        successful_steps += 1;
        let change = cost - new_cost;
        cost = new_cost;
        history.push((cost, start.elapsed().as_secs_f64()));
        let factor = 1.0 - (2.0 * ratio - 1.0).powi(3);
        radius = (radius / factor.max(1.0 / 3.0)).min(options.max_trust_radius);
        nu = 2.0;
        if change <= options.function_tolerance * (cost + change) {
            break Termination::FunctionTolerance;
        }
        gradient_max = problem.linearize();
    };
    Ok(LmReport {
        initial_cost,
        final_cost: cost,
        iterations,
        successful_steps,
        seconds: start.elapsed().as_secs_f64(),
        termination,
        history,
    })
}
