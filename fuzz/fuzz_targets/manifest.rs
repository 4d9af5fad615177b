//! Any bytes given to the package-manifest reader: an error or a checked manifest, never a
//! panic; a manifest that parses re-serialises to one that parses to the same value.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(m) = cpsl_package::PackageManifest::parse(data) {
        let again = cpsl_package::PackageManifest::parse(&m.to_json()).expect("re-parses");
        assert_eq!(again.segments, m.segments);
    }
});
