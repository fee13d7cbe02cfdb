//! The light-table parser (CSV, JSON or .lp) on arbitrary bytes: it never panics, and
//! what it accepts is a usable table (unit, finite directions; positive, finite
//! intensities; unique names; at least 3 rows).

#![no_main]

use libfuzzer_sys::fuzz_target;
use photostereo::core::lights;

fuzz_target!(|data: &[u8]| {
    match lights::parse_bytes(data) {
        Ok(table) => {
            assert!(table.len() >= 3 && table.len() <= lights::MAX_ROWS);
            let mut names = std::collections::HashSet::new();
            for l in &table {
                assert!(!l.name.is_empty());
                assert!(names.insert(l.name.as_str()), "duplicate {:?}", l.name);
                let norm = l.direction.iter().map(|c| c * c).sum::<f64>().sqrt();
                assert!(
                    (norm - 1.0).abs() < 1e-9,
                    "{:?} has norm {norm}",
                    l.direction
                );
                assert!(l.intensity.is_finite() && l.intensity > 0.0);
            }
            let (condition, rank) = lights::conditioning(&table);
            assert!(rank <= 3);
            assert!(!condition.is_nan());
        }
        Err(e) => {
            assert!(!e.to_string().is_empty());
        }
    }
});
