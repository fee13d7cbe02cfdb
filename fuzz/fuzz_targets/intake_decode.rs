//! Image intake on arbitrary bytes (any format the image crate recognises): no panic
//! escapes `intake::decode`, oversized headers are refused before allocating, and what it
//! decodes converts to a luminance plane of the declared size.
//!
//! `intake::decode` turns a panic inside a third-party decoder into a decode error (the
//! service's guarantee), but libFuzzer's panic hook would abort on it before it unwinds.
//! So the hook is replaced with one that only prints: a caught decoder panic is logged and
//! passes, a panic that escapes still aborts (libfuzzer-sys catches it at the top).
//! `PHOTOSTEREO_FUZZ_STRICT=1` keeps libFuzzer's hook, to hunt for decoder panics
//! themselves (each one deserves a check before the decoder, as the PLTE one has).

#![no_main]

use std::sync::Once;

use libfuzzer_sys::fuzz_target;
use photostereo::core::intake::{self, Limits};

const LIMITS: Limits = Limits {
    max_pixels_per_image: 1 << 20,
    max_images: 4,
};

static HOOK: Once = Once::new();

fuzz_target!(|data: &[u8]| {
    HOOK.call_once(|| {
        if std::env::var_os("PHOTOSTEREO_FUZZ_STRICT").is_none() {
            std::panic::set_hook(Box::new(|info| eprintln!("caught decoder panic: {info}")));
        }
    });
    if let Ok(img) = intake::decode("fuzz.img", data, &LIMITS) {
        let (w, h) = (img.width() as usize, img.height() as usize);
        assert!((w * h) as u64 <= LIMITS.max_pixels_per_image);
        let plane = intake::to_luma16(img);
        assert_eq!(plane.dim(), (h, w));
    }
});
