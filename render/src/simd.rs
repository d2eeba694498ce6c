//! Which instruction set the tracer's lane code runs with, and the one place that
//! switches to it.
//!
//! The lane code ([`crate::vec3::F4`] and friends) is written once, as plain arrays the
//! compiler vectorises. Compiled for the baseline x86-64 target it uses 128-bit
//! registers; inside a function compiled with AVX2 enabled, the same source uses 256-bit
//! registers that hold four doubles at once. Both perform the same IEEE operations in
//! the same order (no fused multiply-add: Rust never contracts `a * b + c`), so they
//! give the same bits; only the speed differs. [`isa_dispatch!`] is the single way into
//! the AVX2 build of a piece of code: it defines an entry that runs its body either as
//! is or inside a twin compiled with AVX2 enabled, into which everything
//! `#[inline(always)]` the body calls is inlined. The twin is a named function rather
//! than a closure so that recursion (a packet's reflections) re-enters it directly.
//!
//! `TESSERA_SIMD=portable` in the environment forces the portable code on any
//! processor, for tests that both paths give the same bytes, and for an operator who
//! suspects one of them.

/// The instruction set the lane code is compiled for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Isa {
    /// The baseline of the target: what every processor it runs on has.
    Portable,
    /// x86-64 with AVX2 (256-bit vectors).
    Avx2,
}

/// The environment variable that forces [`Isa::Portable`] when set to `portable`.
pub const SIMD_ENV: &str = "TESSERA_SIMD";

impl Isa {
    /// The fastest instruction set this processor has, unless the environment forces
    /// the portable one ([`SIMD_ENV`]).
    pub fn detect() -> Isa {
        if std::env::var_os(SIMD_ENV).is_some_and(|v| v == "portable") {
            return Isa::Portable;
        }
        Isa::best()
    }

    /// The fastest instruction set this processor has.
    pub fn best() -> Isa {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            return Isa::Avx2;
        }
        Isa::Portable
    }
}

/// Defines, inside the `impl` of a type with an `isa: Isa` field, the method `$entry`
/// running `$body`, and `$avx2`, the same body compiled with AVX2 enabled, which
/// `$entry` calls when `self.isa` is [`Isa::Avx2`]. Keep the body a call of an
/// `#[inline(always)]` method: it is compiled twice.
macro_rules! isa_dispatch {
    (
        $(#[$attr:meta])*
        $vis:vis fn $entry:ident / $avx2:ident $(<$g:ident: $bound:path>)?
            (&$self:ident $(, $arg:ident: $ty:ty)* $(,)?) -> $ret:ty $body:block
    ) => {
        $(#[$attr])*
        #[inline(always)]
        $vis fn $entry $(<$g: $bound>)? (&$self $(, $arg: $ty)*) -> $ret {
            #[cfg(target_arch = "x86_64")]
            if $self.isa == $crate::simd::Isa::Avx2 {
                // SAFETY: an `Isa::Avx2` is only ever made where the processor was
                // found to support AVX2 (`Isa::best`).
                return unsafe { $self.$avx2($($arg),*) };
            }
            $body
        }

        /// The method of the same name without `_avx2`, compiled with AVX2 enabled.
        #[cfg(target_arch = "x86_64")]
        #[target_feature(enable = "avx2")]
        unsafe fn $avx2 $(<$g: $bound>)? (&$self $(, $arg: $ty)*) -> $ret $body
    };
}
pub(crate) use isa_dispatch;
