//! BAL and g2o readers: well-formed files parse to what they say; malformed ones (truncated,
//! NaN, unknown tags, indices out of range, bad information matrices) give a parse error
//! naming the line, never a panic.

use std::path::Path;

use dhptam_core::io::{BalProblem, PoseGraph};
use dhptam_core::Error;

const BAL: &str = "2 2 3
0 0 1.5 -2.0
1 0 0.5 1.0
1 1 -3.0 4.0
0.1
0.2
0.3
1
2
3
500
0.01
0.001
0 0 0 0 0 0 400 0 0
1 2 3
4 5 6
";

fn parse_error_line(result: dhptam_core::Result<impl std::fmt::Debug>) -> (usize, String) {
    match result {
        Err(Error::Parse { line, message, .. }) => (line, message),
        other => panic!("expected a parse error, got {other:?}"),
    }
}

#[test]
fn bal_parses_observations_cameras_and_points() {
    let p = BalProblem::parse(Path::new("t.txt"), BAL).unwrap();
    assert_eq!(p.cameras.len(), 2);
    assert_eq!(
        p.cameras[0],
        [0.1, 0.2, 0.3, 1.0, 2.0, 3.0, 500.0, 0.01, 0.001]
    );
    assert_eq!(p.cameras[1][6], 400.0);
    assert_eq!(p.points, vec![[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]);
    assert_eq!(p.observations[2].camera, 1);
    assert_eq!(p.observations[2].point, 1);
    assert_eq!(p.observations[2].pixel, [-3.0, 4.0]);
    // Written and parsed again, nothing changes.
    let again = BalProblem::parse(Path::new("t.txt"), &p.to_text()).unwrap();
    assert_eq!(again, p);
}

#[test]
fn bal_malformed_files_name_the_line() {
    let cases: Vec<(String, usize, &str)> = vec![
        (BAL.replace("1 0 0.5 1.0", "1 0 nan 1.0"), 3, "finite"),
        (BAL.replace("1 0 0.5 1.0", "1 5 0.5 1.0"), 3, "out of range"),
        (BAL.replace("1 0 0.5 1.0", "7 0 0.5 1.0"), 3, "out of range"),
        (BAL.replace("1 0 0.5 1.0", "1 0 0.5"), 3, "missing"),
        (BAL.replace("1 0 0.5 1.0", "1 0 0.5 1.0 9"), 3, "extra"),
        (BAL.replace("2 2 3", "2 two 3"), 1, "integer"),
        (BAL.replace("0.2\n", "inf\n"), 6, "finite"),
        (BAL.replace("4 5 6\n", "4 5 6 7\n"), 16, "extra"),
        (BAL.replace("4 5 6\n", "4 5\n"), 16, "file ends"),
        (
            BAL.lines().take(2).collect::<Vec<_>>().join("\n"),
            2,
            "file ends",
        ),
        (String::new(), 1, "file ends"),
        ("99999999999 1 1\n".to_string(), 1, "counts"),
    ];
    for (text, line, needle) in cases {
        let (got, message) = parse_error_line(BalProblem::parse(Path::new("bad.txt"), &text));
        assert_eq!(got, line, "{message}");
        assert!(
            message.contains(needle),
            "{message:?} should mention {needle:?}"
        );
    }
}

#[test]
fn bal_missing_file_is_an_io_error() {
    match BalProblem::read("/nonexistent/problem-1-1-1.txt") {
        Err(Error::Io { path, .. }) => assert!(path.ends_with("problem-1-1-1.txt")),
        other => panic!("{other:?}"),
    }
}

const SE3: &str = "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1
VERTEX_SE3:QUAT 5 1 0 0 0 0 0.0998334 0.9950042
# a comment
EDGE_SE3:QUAT 0 5 1 0 0 0 0 0 1 1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 2 0 0 2 0 2
FIX 0
";

const SE2: &str = "VERTEX_SE2 0 0 0 0
VERTEX_SE2 1 1 0 0.1
EDGE_SE2 0 1 1 0 0.1 10 0 0 10 0 100
";

#[test]
fn g2o_parses_se3_and_se2_graphs() {
    let PoseGraph::Se3(g) = PoseGraph::parse(Path::new("g.g2o"), SE3).unwrap() else {
        panic!("SE3 expected")
    };
    assert_eq!(g.ids, vec![0, 5]);
    assert_eq!(g.fixed, vec![0]);
    assert_eq!((g.edges[0].from, g.edges[0].to), (0, 1));
    assert_eq!(g.edges[0].information[(3, 3)], 2.0);
    assert_eq!(g.edges[0].information[(1, 1)], 1.0);
    let PoseGraph::Se2(g) = PoseGraph::parse(Path::new("g.g2o"), SE2).unwrap() else {
        panic!("SE2 expected")
    };
    assert_eq!(g.poses[1].theta, 0.1);
    assert_eq!(g.edges[0].information[(2, 2)], 100.0);
    // Writing and reading again keeps the graph.
    let graph = PoseGraph::Se2(g);
    assert_eq!(
        PoseGraph::parse(Path::new("g.g2o"), &graph.to_text()).unwrap(),
        graph
    );
}

#[test]
fn g2o_malformed_files_name_the_line() {
    let cases: Vec<(String, usize, &str)> = vec![
        (SE3.replace("FIX 0", "VERTEX_XYZ 3 0 0 0"), 5, "unknown tag"),
        (
            SE3.replace("EDGE_SE3:QUAT 0 5", "EDGE_SE3:QUAT 0 6"),
            4,
            "not a vertex",
        ),
        (
            SE3.replace("EDGE_SE3:QUAT 0 5 1", "EDGE_SE3:QUAT 0 5 NaN"),
            4,
            "finite",
        ),
        (SE3.replace(" 0 2 0 2\n", " 0 2 0\n"), 4, "missing"),
        (
            SE3.replace(
                "VERTEX_SE3:QUAT 5 1 0 0 0 0 0.0998334 0.9950042",
                "VERTEX_SE3:QUAT 5 1 0 0 0 0",
            ),
            2,
            "missing",
        ),
        (
            SE3.replace("0 0 0 0 0 1\nVERTEX", "0 0 0 0 0 0\nVERTEX"),
            1,
            "quaternion",
        ),
        (SE3.replace("FIX 0", "FIX 9"), 5, "not defined"),
        (
            SE3.replace(
                "EDGE_SE3:QUAT 0 5 1 0 0 0 0 0 1 1",
                "EDGE_SE3:QUAT 0 5 1 0 0 0 0 0 1 -1",
            ),
            4,
            "positive definite",
        ),
        (
            SE3.replace("VERTEX_SE3:QUAT 5", "VERTEX_SE3:QUAT 0"),
            2,
            "twice",
        ),
        (
            SE3.replace("EDGE_SE3:QUAT 0 5", "EDGE_SE3:QUAT 5 5"),
            4,
            "different",
        ),
        (format!("{SE3}VERTEX_SE2 7 0 0 0\n"), 6, "either"),
        (SE2.replace("10 0 100", "10 0 100 5"), 3, "extra"),
        (
            SE2.replace("VERTEX_SE2 1 1 0 0.1", "VERTEX_SE2 -1 1 0 0.1"),
            2,
            "integer",
        ),
        ("# only a comment\n".to_string(), 1, "no vertices"),
    ];
    for (text, line, needle) in cases {
        let (got, message) = parse_error_line(PoseGraph::parse(Path::new("bad.g2o"), &text));
        assert_eq!(got, line, "{message}");
        assert!(
            message.contains(needle),
            "{message:?} should mention {needle:?}"
        );
    }
}
