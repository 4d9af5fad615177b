//! Any bytes given to the side-stream reader: an error or a validated stream, never a panic;
//! a stream that decodes re-encodes to one that decodes to the same value.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(s) = cpsl_package::SideStream::decode(data) {
        let again = cpsl_package::SideStream::decode(&s.encode()).expect("re-decodes");
        assert_eq!(again, s);
    }
});
