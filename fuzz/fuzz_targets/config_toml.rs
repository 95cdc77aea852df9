//! Configuration TOML: any text gives a `Config` or `Error::Config`, never a panic; an
//! accepted configuration round-trips through the TOML dhptam writes.
#![no_main]

use dhptam_core::config::Config;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    if let Ok(config) = Config::from_toml_str(text, "fuzz.toml") {
        let written = config.to_toml();
        let again = Config::from_toml_str(&written, "written.toml")
            .expect("a configuration dhptam wrote must load again");
        assert_eq!(again.to_toml(), written);
    }
});
