//! g2o pose-graph files: 3-D (`VERTEX_SE3:QUAT`, `EDGE_SE3:QUAT`) and planar (`VERTEX_SE2`,
//! `EDGE_SE2`) graphs, plus `FIX id` lines.
//!
//! ```text
//! VERTEX_SE3:QUAT id x y z qx qy qz qw                    world_from_vertex
//! EDGE_SE3:QUAT i j x y z qx qy qz qw  Ω₁₁ Ω₁₂ … Ω₆₆      i_from_j, upper triangle of Ω (21)
//! VERTEX_SE2 id x y θ
//! EDGE_SE2 i j x y θ  Ω₁₁ Ω₁₂ Ω₁₃ Ω₂₂ Ω₂₃ Ω₃₃
//! ```
//!
//! Ω is the information matrix of the error in the order (translation, rotation). A file holds
//! one kind of graph; vertex ids may be any non-negative integers and are kept for writing.

use std::collections::HashMap;
use std::fmt::Write as _;
use std::path::Path;

use nalgebra::{Matrix3, Matrix6, Vector3};

use super::text::{read_to_string, write_atomically, Line};
use crate::error::{Error, Result};
use crate::geometry::{Se3, So3};

/// A planar pose (x, y, θ): `world_from_vertex` maps p to R(θ) p + (x, y).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Pose2 {
    /// Translation x.
    pub x: f64,
    /// Translation y.
    pub y: f64,
    /// Heading, radians.
    pub theta: f64,
}

/// A relative-pose constraint between vertices `from` and `to` (indices into the vertex list).
#[derive(Clone, Debug, PartialEq)]
pub struct EdgeSe3 {
    /// Index of vertex i.
    pub from: usize,
    /// Index of vertex j.
    pub to: usize,
    /// The measured `i_from_j`.
    pub measurement: Se3,
    /// Information matrix of the error [ρ, φ].
    pub information: Matrix6<f64>,
}

/// A planar relative-pose constraint.
#[derive(Clone, Debug, PartialEq)]
pub struct EdgeSe2 {
    /// Index of vertex i.
    pub from: usize,
    /// Index of vertex j.
    pub to: usize,
    /// The measured `i_from_j`.
    pub measurement: Pose2,
    /// Information matrix of the error [x, y, θ].
    pub information: Matrix3<f64>,
}

/// A 3-D pose graph.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PoseGraph3 {
    /// Vertex ids as in the file.
    pub ids: Vec<usize>,
    /// `world_from_vertex` per vertex.
    pub poses: Vec<Se3>,
    /// Constraints.
    pub edges: Vec<EdgeSe3>,
    /// Indices of vertices marked `FIX`.
    pub fixed: Vec<usize>,
}

/// A planar pose graph.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PoseGraph2 {
    /// Vertex ids as in the file.
    pub ids: Vec<usize>,
    /// `world_from_vertex` per vertex.
    pub poses: Vec<Pose2>,
    /// Constraints.
    pub edges: Vec<EdgeSe2>,
    /// Indices of vertices marked `FIX`.
    pub fixed: Vec<usize>,
}

/// Either kind of graph, as found in a file.
#[derive(Clone, Debug, PartialEq)]
pub enum PoseGraph {
    /// `VERTEX_SE3:QUAT` / `EDGE_SE3:QUAT`.
    Se3(PoseGraph3),
    /// `VERTEX_SE2` / `EDGE_SE2`.
    Se2(PoseGraph2),
}

/// Reads the symmetric matrix from its row-major upper triangle.
fn upper_triangle<const N: usize>(line: &mut Line<'_>) -> Result<nalgebra::SMatrix<f64, N, N>> {
    let mut m = nalgebra::SMatrix::<f64, N, N>::zeros();
    for r in 0..N {
        for c in r..N {
            let v = line.float(&format!("information[{r}][{c}]"))?;
            m[(r, c)] = v;
            m[(c, r)] = v;
        }
    }
    if m.cholesky().is_none() {
        return Err(line.error("information matrix is not positive definite"));
    }
    Ok(m)
}

fn write_upper<const N: usize>(s: &mut String, m: &nalgebra::SMatrix<f64, N, N>) {
    for r in 0..N {
        for c in r..N {
            let _ = write!(s, " {}", m[(r, c)]);
        }
    }
}

impl PoseGraph {
    /// Reads a g2o file.
    pub fn read(path: impl AsRef<Path>) -> Result<Self> {
        let path = path.as_ref();
        let text = read_to_string(path)?;
        Self::parse(path, &text)
    }

    /// Parses g2o text; `path` only names the source in errors.
    pub fn parse(path: &Path, text: &str) -> Result<Self> {
        let mut ids: Vec<usize> = Vec::new();
        let mut index: HashMap<usize, usize> = HashMap::new();
        let mut poses3 = Vec::new();
        let mut poses2 = Vec::new();
        let mut edges3 = Vec::new();
        let mut edges2 = Vec::new();
        let mut fixed_ids: Vec<(usize, usize)> = Vec::new();
        let mut planar: Option<bool> = None;
        for (i, l) in text.lines().enumerate() {
            let n = i + 1;
            let mut line = Line::new(path, n, l);
            let Ok(tag) = line.token("tag") else {
                continue;
            };
            if tag.starts_with('#') {
                continue;
            }
            let kind = match tag {
                "VERTEX_SE3:QUAT" | "EDGE_SE3:QUAT" => Some(false),
                "VERTEX_SE2" | "EDGE_SE2" => Some(true),
                "FIX" => None,
                other => return Err(line.error(format!("unknown tag {other:?}"))),
            };
            if let Some(k) = kind {
                match planar {
                    Some(p) if p != k => {
                        return Err(line.error("a file holds either SE2 or SE3 elements, not both"))
                    }
                    _ => planar = Some(k),
                }
            }
            match tag {
                "VERTEX_SE3:QUAT" | "VERTEX_SE2" => {
                    let id = line.index("vertex id", None)?;
                    if index.contains_key(&id) {
                        return Err(line.error(format!("vertex {id} defined twice")));
                    }
                    if tag == "VERTEX_SE2" {
                        let x = line.float("x")?;
                        let y = line.float("y")?;
                        let theta = line.float("theta")?;
                        poses2.push(Pose2 { x, y, theta });
                    } else {
                        poses3.push(read_se3(&mut line)?);
                    }
                    index.insert(id, ids.len());
                    ids.push(id);
                }
                "EDGE_SE3:QUAT" | "EDGE_SE2" => {
                    let vertex = |line: &mut Line<'_>, what: &str| -> Result<usize> {
                        let id = line.index(what, None)?;
                        index.get(&id).copied().ok_or_else(|| {
                            line.error(format!("{what} {id} is not a vertex defined above"))
                        })
                    };
                    let from = vertex(&mut line, "vertex i")?;
                    let to = vertex(&mut line, "vertex j")?;
                    if from == to {
                        return Err(line.error("an edge must join two different vertices"));
                    }
                    if tag == "EDGE_SE2" {
                        let x = line.float("x")?;
                        let y = line.float("y")?;
                        let theta = line.float("theta")?;
                        let information = upper_triangle::<3>(&mut line)?;
                        edges2.push(EdgeSe2 {
                            from,
                            to,
                            measurement: Pose2 { x, y, theta },
                            information,
                        });
                    } else {
                        let measurement = read_se3(&mut line)?;
                        let information = upper_triangle::<6>(&mut line)?;
                        edges3.push(EdgeSe3 {
                            from,
                            to,
                            measurement,
                            information,
                        });
                    }
                }
                _ => {
                    let id = line.index("vertex id", None)?;
                    fixed_ids.push((n, id));
                }
            }
            line.finish()?;
        }
        let mut fixed = Vec::new();
        for (n, id) in fixed_ids {
            match index.get(&id) {
                Some(&k) => fixed.push(k),
                None => {
                    return Err(Error::Parse {
                        path: path.to_path_buf(),
                        line: n,
                        message: format!("FIX names vertex {id}, which is not defined"),
                    })
                }
            }
        }
        if ids.is_empty() {
            return Err(Error::Parse {
                path: path.to_path_buf(),
                line: text.lines().count().max(1),
                message: "no vertices in the file".into(),
            });
        }
        Ok(if planar == Some(true) {
            PoseGraph::Se2(PoseGraph2 {
                ids,
                poses: poses2,
                edges: edges2,
                fixed,
            })
        } else {
            PoseGraph::Se3(PoseGraph3 {
                ids,
                poses: poses3,
                edges: edges3,
                fixed,
            })
        })
    }

    /// The graph as g2o text (vertices first, then edges, then `FIX` lines).
    pub fn to_text(&self) -> String {
        let mut s = String::new();
        match self {
            PoseGraph::Se3(g) => {
                for (id, p) in g.ids.iter().zip(&g.poses) {
                    let _ = write!(s, "VERTEX_SE3:QUAT {id}");
                    write_se3(&mut s, p);
                    s.push('\n');
                }
                for e in &g.edges {
                    let _ = write!(s, "EDGE_SE3:QUAT {} {}", g.ids[e.from], g.ids[e.to]);
                    write_se3(&mut s, &e.measurement);
                    write_upper(&mut s, &e.information);
                    s.push('\n');
                }
                for &k in &g.fixed {
                    let _ = writeln!(s, "FIX {}", g.ids[k]);
                }
            }
            PoseGraph::Se2(g) => {
                for (id, p) in g.ids.iter().zip(&g.poses) {
                    let _ = writeln!(s, "VERTEX_SE2 {id} {} {} {}", p.x, p.y, p.theta);
                }
                for e in &g.edges {
                    let m = &e.measurement;
                    let _ = write!(
                        s,
                        "EDGE_SE2 {} {} {} {} {}",
                        g.ids[e.from], g.ids[e.to], m.x, m.y, m.theta
                    );
                    write_upper(&mut s, &e.information);
                    s.push('\n');
                }
                for &k in &g.fixed {
                    let _ = writeln!(s, "FIX {}", g.ids[k]);
                }
            }
        }
        s
    }

    /// Writes the graph as a g2o file.
    pub fn write(&self, path: impl AsRef<Path>) -> Result<()> {
        write_atomically(path.as_ref(), &self.to_text())
    }
}

fn read_se3(line: &mut Line<'_>) -> Result<Se3> {
    let t = Vector3::new(line.float("x")?, line.float("y")?, line.float("z")?);
    let q = [
        line.float("qx")?,
        line.float("qy")?,
        line.float("qz")?,
        line.float("qw")?,
    ];
    let rotation =
        So3::from_quaternion_xyzw(q).map_err(|e| line.error(format!("quaternion: {e}")))?;
    Ok(Se3::new(rotation, t))
}

fn write_se3(s: &mut String, p: &Se3) {
    let t = p.translation;
    let q = p.rotation.to_quaternion_xyzw();
    let _ = write!(
        s,
        " {} {} {} {} {} {} {}",
        t.x, t.y, t.z, q[0], q[1], q[2], q[3]
    );
}
