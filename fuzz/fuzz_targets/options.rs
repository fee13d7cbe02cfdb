//! The `options` part: parsing never panics (the core's serde parse and the service's
//! checked one), the service refuses with a 422 naming the options, and what it accepts
//! survives the trip a job gives it (stored as JSON, read back by the worker) unchanged.

#![no_main]

use libfuzzer_sys::fuzz_target;
use photostereo::core::Options;
use photostereo::service::parse_options;

fuzz_target!(|data: &[u8]| {
    let core = serde_json::from_slice::<Options>(data);
    match parse_options(data) {
        Ok(options) => {
            assert!(core.is_ok(), "the service accepts what the core refuses");
            let stored = serde_json::to_value(&options).expect("options serialise");
            let again: Options = serde_json::from_value(stored).expect("stored options parse");
            assert_eq!(options, again);
        }
        Err(e) => {
            assert_eq!(e.status().as_u16(), 422, "{e}");
            assert!(e.detail().starts_with("options: "), "{e}");
        }
    }
});
