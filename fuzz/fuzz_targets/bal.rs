//! BAL problem files: any text must parse or give `Error::Parse`, never panic; a parsed
//! problem must survive a write/parse round trip with the same sizes.
#![no_main]

use std::path::Path;

use dhptam_core::io::BalProblem;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let path = Path::new("fuzz.bal");
    if let Ok(problem) = BalProblem::parse(path, text) {
        let again = BalProblem::parse(path, &problem.to_text())
            .expect("a problem dhptam wrote must parse again");
        assert_eq!(again.cameras.len(), problem.cameras.len());
        assert_eq!(again.points.len(), problem.points.len());
        assert_eq!(again.observations.len(), problem.observations.len());
    }
});
