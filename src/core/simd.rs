//! Runtime dispatch to AVX2 copies of hot loops.
//!
//! The crate is built for baseline x86-64 (SSE2) so that one binary runs everywhere;
//! [`multiversion!`] compiles a loop body a second time with AVX2 enabled (8-wide f32
//! instead of 4) and picks that copy when the CPU has it.

/// Defines a dispatching function over an `#[inline(always)]` body, optionally generic over
/// one type: on x86-64 CPUs with AVX2 the body is compiled a second time with AVX2 enabled
/// and that copy runs. Results are bit-identical: Rust never contracts `a * b + c` into an
/// FMA, with or without the feature.
macro_rules! multiversion {
    ($(#[$m:meta])* fn $name:ident $(<$g:ident: $bound:path>)? ($($arg:ident: $ty:ty),* $(,)?) -> $ret:ty => $body:ident) => {
        $(#[$m])*
        #[allow(clippy::too_many_arguments)]
        fn $name $(<$g: $bound>)? ($($arg: $ty),*) -> $ret {
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx2")]
                #[allow(clippy::too_many_arguments)]
                fn avx2 $(<$g: $bound>)? ($($arg: $ty),*) -> $ret {
                    $body($($arg),*)
                }
                if std::arch::is_x86_feature_detected!("avx2") {
                    // SAFETY: the CPU supports AVX2, checked just above.
                    return unsafe { avx2($($arg),*) };
                }
            }
            $body($($arg),*)
        }
    };
}
