//! Image intake on arbitrary bytes (any format the image crate recognises): never panics,
//! refuses oversized headers before allocating, and what it decodes converts to a
//! luminance plane of the declared size.

#![no_main]

use libfuzzer_sys::fuzz_target;
use photostereo::core::intake::{self, Limits};

const LIMITS: Limits = Limits {
    max_pixels_per_image: 1 << 20,
    max_images: 4,
};

fuzz_target!(|data: &[u8]| {
    if let Ok(img) = intake::decode("fuzz.img", data, &LIMITS) {
        let (w, h) = (img.width() as usize, img.height() as usize);
        assert!((w * h) as u64 <= LIMITS.max_pixels_per_image);
        let plane = intake::to_luma16(img);
        assert_eq!(plane.dim(), (h, w));
    }
});
