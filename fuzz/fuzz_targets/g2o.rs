//! g2o pose graphs (SE(3) and SE(2)): any text must parse or give `Error::Parse`, never
//! panic; a parsed graph must parse again from what dhptam writes.
#![no_main]

use std::path::Path;

use dhptam_core::io::PoseGraph;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let path = Path::new("fuzz.g2o");
    if let Ok(graph) = PoseGraph::parse(path, text) {
        PoseGraph::parse(path, &graph.to_text()).expect("a graph dhptam wrote must parse again");
    }
});
