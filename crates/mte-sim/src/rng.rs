//! Bit-exact reproductions of the numpy random streams that PushT's seeded resets draw from.
//!
//! Two streams matter:
//!
//! * [`LegacyRandomState`]: `numpy.random.RandomState(seed)`, the MT19937 generator with
//!   numpy's *legacy* distributions. Diffusion Policy's `PushTEnv` and gym-pusht <= 0.1.5
//!   build one per seeded reset.
//! * [`NumpyGenerator`]: `numpy.random.Generator(PCG64(SeedSequence(seed)))`, what
//!   gymnasium's `np_random(seed)` builds and gym-pusht >= 0.1.6 draws from.
//!
//! [`ResetStream`] selects one and produces the five raw draws of a PushT reset.
//!
//! Conventions: every method consumes exactly the words numpy's C code consumes, in the same
//! order, so interleaving calls stays in lock step with numpy. Integer ranges are half-open
//! `[low, high)` (numpy's default `endpoint=False`) and returned as `i64` (numpy's default
//! `int64` dtype). Nothing here panics: invalid arguments return [`RngError`].
//!
//! The algorithms follow numpy 2.2.6's C sources (`mt19937.c`, `pcg64.h`,
//! `legacy-distributions.c`, `distributions.c`, `bit_generator.pyx`); the reference values in
//! `tests/fixtures/numpy_rng.json` come from `tools/reference/numpy_rng_reference.py`.

use std::f64::consts::PI;
use std::fmt;
use std::str::FromStr;

/// Errors from the generators: arguments numpy would reject with `ValueError` or
/// `OverflowError`.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RngError {
    /// An integer range `[low, high)` with `low >= high` (numpy: `ValueError: low >= high`).
    #[error("empty integer range: low ({low}) >= high ({high})")]
    EmptyIntRange {
        /// Inclusive lower bound that was passed.
        low: i64,
        /// Exclusive upper bound that was passed.
        high: i64,
    },
    /// `uniform(low, high)` where `high - low` is not finite (infinite or NaN bounds, or an
    /// overflowing difference). numpy: `OverflowError: high - low range exceeds valid bounds`.
    #[error("uniform range is not finite: low = {low}, high = {high}")]
    UniformNotFinite {
        /// Lower bound that was passed.
        low: f64,
        /// Upper bound that was passed.
        high: f64,
    },
    /// `uniform(low, high)` with `high < low` (numpy: `ValueError: high - low < 0`).
    #[error("uniform range is reversed: high ({high}) < low ({low})")]
    UniformReversed {
        /// Lower bound that was passed.
        low: f64,
        /// Upper bound that was passed.
        high: f64,
    },
    /// A `RandomState` seed above `2**32 - 1` (numpy: `ValueError: Seed must be between 0 and
    /// 2**32 - 1`).
    #[error("legacy RandomState seed {seed} is out of range 0..=4294967295")]
    LegacySeedOutOfRange {
        /// The seed that was passed.
        seed: u64,
    },
}

// ---------------------------------------------------------------------------------------------
// Bounded integers (numpy `distributions.c`, `random_bounded_uint64_fill`).
// ---------------------------------------------------------------------------------------------

/// The two word sources the bounded-integer samplers need.
trait Words {
    fn word32(&mut self) -> u32;
    fn word64(&mut self) -> u64;
}

/// Smallest all-ones bit mask `>= max` (numpy `gen_mask`).
fn gen_mask(max: u64) -> u64 {
    let mut mask = max;
    mask |= mask >> 1;
    mask |= mask >> 2;
    mask |= mask >> 4;
    mask |= mask >> 8;
    mask |= mask >> 16;
    mask |= mask >> 32;
    mask
}

/// `buffered_bounded_masked_uint32`: masked rejection on 32-bit draws, `rng < 2**32 - 1`.
fn masked_u32<W: Words>(w: &mut W, rng: u32) -> u32 {
    // gen_mask of a value < 2**32 is < 2**32, so the cast is lossless.
    let mask = gen_mask(u64::from(rng)) as u32;
    loop {
        let val = w.word32() & mask;
        if val <= rng {
            return val;
        }
    }
}

/// `bounded_masked_uint64`: masked rejection on 64-bit draws.
fn masked_u64<W: Words>(w: &mut W, rng: u64) -> u64 {
    let mask = gen_mask(rng);
    loop {
        let val = w.word64() & mask;
        if val <= rng {
            return val;
        }
    }
}

/// `buffered_bounded_lemire_uint32`: Lemire's multiply-shift with rejection, `rng < 2**32 - 1`.
fn lemire_u32<W: Words>(w: &mut W, rng: u32) -> u32 {
    let rng_excl = rng.wrapping_add(1);
    let mut m = u64::from(w.word32()) * u64::from(rng_excl);
    let mut leftover = m as u32;
    if leftover < rng_excl {
        // rng_excl > 0 because callers never pass rng == u32::MAX.
        let threshold = (u32::MAX - rng).checked_rem(rng_excl).unwrap_or(0);
        while leftover < threshold {
            m = u64::from(w.word32()) * u64::from(rng_excl);
            leftover = m as u32;
        }
    }
    (m >> 32) as u32
}

/// `bounded_lemire_uint64`: Lemire's multiply-shift with rejection, `rng < 2**64 - 1`.
fn lemire_u64<W: Words>(w: &mut W, rng: u64) -> u64 {
    let rng_excl = rng.wrapping_add(1);
    let mut m = u128::from(w.word64()) * u128::from(rng_excl);
    let mut leftover = m as u64;
    if leftover < rng_excl {
        let threshold = (u64::MAX - rng).checked_rem(rng_excl).unwrap_or(0);
        while leftover < threshold {
            m = u128::from(w.word64()) * u128::from(rng_excl);
            leftover = m as u64;
        }
    }
    (m >> 64) as u64
}

/// numpy's `_rand_int64(low, high, size=None, use_masked, endpoint=False)` followed by
/// `random_bounded_uint64_fill(off = low, rng = high - 1 - low, cnt = 1)`.
fn bounded_i64<W: Words>(w: &mut W, low: i64, high: i64, masked: bool) -> Result<i64, RngError> {
    if low >= high {
        return Err(RngError::EmptyIntRange { low, high });
    }
    // Two's-complement arithmetic on the bit patterns, exactly as numpy's uint64 casts.
    let off = low as u64;
    let rng = (high as u64).wrapping_sub(1).wrapping_sub(off);
    let val = if rng == 0 {
        0
    } else if rng < u64::from(u32::MAX) {
        let rng32 = rng as u32;
        u64::from(if masked {
            masked_u32(w, rng32)
        } else {
            lemire_u32(w, rng32)
        })
    } else if rng == u64::from(u32::MAX) {
        u64::from(w.word32())
    } else if rng == u64::MAX {
        // Unreachable with an exclusive `high` (the widest range is 2**64 - 2), kept to mirror
        // numpy: Lemire cannot handle rng == 2**64 - 1.
        w.word64()
    } else if masked {
        masked_u64(w, rng)
    } else {
        lemire_u64(w, rng)
    };
    Ok(off.wrapping_add(val) as i64)
}

// ---------------------------------------------------------------------------------------------
// MT19937 and RandomState.
// ---------------------------------------------------------------------------------------------

const MT_N: usize = 624;
const MT_M: usize = 397;
const MT_MATRIX_A: u32 = 0x9908_b0df;
const MT_UPPER_MASK: u32 = 0x8000_0000;
const MT_LOWER_MASK: u32 = 0x7fff_ffff;

/// `numpy.random.RandomState(seed)`: MT19937 seeded with Matsumoto–Nishimura `init_genrand`
/// (numpy's `mt19937_seed`, the path an integer seed takes), with numpy's legacy
/// distributions.
///
/// State: the 624-word MT key, the read position, and the cached second value of the polar
/// Box–Muller pair used by [`LegacyRandomState::randn`] (numpy's `has_gauss` / `gauss`).
#[derive(Clone, Debug)]
pub struct LegacyRandomState {
    key: [u32; MT_N],
    pos: usize,
    gauss: Option<f64>,
}

impl LegacyRandomState {
    /// `RandomState(seed)` for an integer seed: `key[0] = seed`,
    /// `key[i] = 1812433253 * (key[i-1] ^ (key[i-1] >> 30)) + i` (mod 2**32); the first draw
    /// regenerates the whole key. The gauss cache starts empty.
    pub fn new(seed: u32) -> Self {
        let mut key = [0_u32; MT_N];
        let mut s = seed;
        for (i, k) in key.iter_mut().enumerate() {
            *k = s;
            // i + 1 <= 624, so the cast is lossless.
            s = 1_812_433_253_u32
                .wrapping_mul(s ^ (s >> 30))
                .wrapping_add(i as u32 + 1);
        }
        Self {
            key,
            pos: MT_N,
            gauss: None,
        }
    }

    /// Regenerates the key (numpy `mt19937_gen`).
    fn generate(&mut self) {
        for i in 0..MT_N {
            let y = (self.key[i] & MT_UPPER_MASK) | (self.key[(i + 1) % MT_N] & MT_LOWER_MASK);
            let mag = if y & 1 == 1 { MT_MATRIX_A } else { 0 };
            self.key[i] = self.key[(i + MT_M) % MT_N] ^ (y >> 1) ^ mag;
        }
        self.pos = 0;
    }

    /// The next tempered 32-bit MT19937 output (numpy `mt19937_next32`; what
    /// `MT19937.random_raw()` and `RandomState.randint(0, 2**32)` return).
    pub fn next_u32(&mut self) -> u32 {
        if self.pos >= MT_N {
            self.generate();
        }
        let mut y = self.key[self.pos];
        self.pos += 1;
        y ^= y >> 11;
        y ^= (y << 7) & 0x9d2c_5680;
        y ^= (y << 15) & 0xefc6_0000;
        y ^ (y >> 18)
    }

    /// numpy `mt19937_next64`: two 32-bit outputs, the first in the high half.
    fn next_u64(&mut self) -> u64 {
        let hi = u64::from(self.next_u32());
        let lo = u64::from(self.next_u32());
        (hi << 32) | lo
    }

    /// `RandomState.random_sample()`: a double in `[0, 1)` from two 32-bit outputs `a`, `b`:
    /// `((a >> 5) * 2**26 + (b >> 6)) / 2**53` (numpy `mt19937_next_double`).
    pub fn random_f64(&mut self) -> f64 {
        let a = self.next_u32() >> 5;
        let b = self.next_u32() >> 6;
        (f64::from(a) * 67_108_864.0 + f64::from(b)) / 9_007_199_254_740_992.0
    }

    /// `RandomState.randint(low, high)` with the default `int64` dtype: an integer in
    /// `[low, high)`.
    ///
    /// With `rng = high - 1 - low`: `rng == 0` returns `low` without drawing; `rng < 2**32 - 1`
    /// uses masked rejection on 32-bit draws (numpy `buffered_bounded_masked_uint32`);
    /// `rng == 2**32 - 1` adds one raw 32-bit draw; wider ranges use masked rejection on
    /// 64-bit draws (`bounded_masked_uint64`, each 64-bit draw being two 32-bit outputs,
    /// high half first).
    ///
    /// # Errors
    /// [`RngError::EmptyIntRange`] when `low >= high`.
    pub fn randint(&mut self, low: i64, high: i64) -> Result<i64, RngError> {
        bounded_i64(self, low, high, true)
    }

    /// `RandomState.randn()`: a standard normal by numpy's `legacy_gauss`, the polar
    /// Box–Muller method. Draws `x1 = 2u - 1`, `x2 = 2u - 1` (each `u` a
    /// [`random_f64`](Self::random_f64)) until `0 < r2 = x1^2 + x2^2 < 1`, returns
    /// `x2 * f` with `f = sqrt(-2 ln(r2) / r2)` and caches `x1 * f` for the next call. Other
    /// draws leave the cache alone, as in numpy.
    pub fn randn(&mut self) -> f64 {
        if let Some(g) = self.gauss.take() {
            return g;
        }
        loop {
            let x1 = 2.0 * self.random_f64() - 1.0;
            let x2 = 2.0 * self.random_f64() - 1.0;
            let r2 = x1 * x1 + x2 * x2;
            if r2 < 1.0 && r2 != 0.0 {
                let f = (-2.0 * r2.ln() / r2).sqrt();
                self.gauss = Some(f * x1);
                return f * x2;
            }
        }
    }
}

impl Words for LegacyRandomState {
    fn word32(&mut self) -> u32 {
        self.next_u32()
    }
    fn word64(&mut self) -> u64 {
        self.next_u64()
    }
}

// ---------------------------------------------------------------------------------------------
// SeedSequence.
// ---------------------------------------------------------------------------------------------

const SS_POOL_SIZE: usize = 4;
const SS_INIT_A: u32 = 0x43b0_d7e5;
const SS_MULT_A: u32 = 0x931e_8875;
const SS_INIT_B: u32 = 0x8b51_f9dd;
const SS_MULT_B: u32 = 0x58f3_8ded;
const SS_MIX_MULT_L: u32 = 0xca01_f9dd;
const SS_MIX_MULT_R: u32 = 0x4973_f715;
const SS_XSHIFT: u32 = 16;

/// `hashmix`: all arithmetic is mod 2**32; `hash_const` advances on every call.
fn ss_hashmix(value: u32, hash_const: &mut u32) -> u32 {
    let mut v = value ^ *hash_const;
    *hash_const = hash_const.wrapping_mul(SS_MULT_A);
    v = v.wrapping_mul(*hash_const);
    v ^ (v >> SS_XSHIFT)
}

/// `mix`.
fn ss_mix(x: u32, y: u32) -> u32 {
    let r = SS_MIX_MULT_L
        .wrapping_mul(x)
        .wrapping_sub(SS_MIX_MULT_R.wrapping_mul(y));
    r ^ (r >> SS_XSHIFT)
}

/// `numpy.random.SeedSequence(entropy).generate_state(n_words_u32, np.uint32)`, with no spawn
/// key and the default pool size of 4 words.
///
/// `entropy` is the entropy as little-endian 32-bit words, the way numpy coerces an integer:
/// `0 -> [0]`, otherwise the base-2**32 digits from least significant, without leading
/// zero words (`2**40 + 7 -> [7, 256]`); see [`seed_entropy_words`]. All arithmetic is
/// mod 2**32.
///
/// Pool mixing (`mix_entropy`), with `hashmix(v)`: `v ^= h; h *= MULT_A; v *= h;
/// v ^= v >> 16` over a running `h = INIT_A = 0x43b0d7e5`, `MULT_A = 0x931e8875`, and
/// `mix(x, y) = (0xca01f9dd * x - 0x4973f715 * y) ^ (... >> 16)`:
/// 1. `pool[i] = hashmix(entropy[i])` for `i < 4` (`hashmix(0)` past the end of `entropy`);
/// 2. for each source `s` and each destination `d != s`:
///    `pool[d] = mix(pool[d], hashmix(pool[s]))`;
/// 3. each remaining entropy word `e` (index >= 4) is folded into every pool word:
///    `pool[d] = mix(pool[d], hashmix(e))`.
///
/// Output (`generate_state`): with `h = INIT_B = 0x8b51f9dd`, for each output word `k`,
/// cycling over the pool: `v = pool[k % 4] ^ h; h *= MULT_B (0x58f38ded); v *= h;
/// out[k] = v ^ (v >> 16)`. numpy's `generate_state(n, np.uint64)` is these `2n` words read
/// in pairs, low word first.
pub fn seed_sequence_words(entropy: &[u32], n_words_u32: usize) -> Vec<u32> {
    let pool = seed_sequence_pool(entropy);
    let mut hash_const = SS_INIT_B;
    pool.iter()
        .cycle()
        .take(n_words_u32)
        .map(|&p| {
            let mut v = p ^ hash_const;
            hash_const = hash_const.wrapping_mul(SS_MULT_B);
            v = v.wrapping_mul(hash_const);
            v ^ (v >> SS_XSHIFT)
        })
        .collect()
}

/// `SeedSequence.pool`: the mixed 4-word entropy pool (steps 1-3 of [`seed_sequence_words`]).
fn seed_sequence_pool(entropy: &[u32]) -> [u32; SS_POOL_SIZE] {
    let mut pool = [0_u32; SS_POOL_SIZE];
    let mut hash_const = SS_INIT_A;
    for (i, p) in pool.iter_mut().enumerate() {
        *p = ss_hashmix(entropy.get(i).copied().unwrap_or(0), &mut hash_const);
    }
    for i_src in 0..SS_POOL_SIZE {
        for i_dst in 0..SS_POOL_SIZE {
            if i_src != i_dst {
                let h = ss_hashmix(pool[i_src], &mut hash_const);
                pool[i_dst] = ss_mix(pool[i_dst], h);
            }
        }
    }
    for &e in entropy.iter().skip(SS_POOL_SIZE) {
        for p in pool.iter_mut() {
            let h = ss_hashmix(e, &mut hash_const);
            *p = ss_mix(*p, h);
        }
    }
    pool
}

/// The entropy words numpy's `SeedSequence` takes from a non-negative integer seed:
/// `[0]` for 0, otherwise the little-endian 32-bit digits without leading zero words
/// (`1 -> [1]`, `2**40 + 7 -> [7, 256]`).
pub fn seed_entropy_words(seed: u64) -> Vec<u32> {
    // Truncating casts pick out the low and high 32-bit digits.
    let lo = seed as u32;
    let hi = (seed >> 32) as u32;
    if hi == 0 { vec![lo] } else { vec![lo, hi] }
}

// ---------------------------------------------------------------------------------------------
// PCG64 and Generator.
// ---------------------------------------------------------------------------------------------

/// PCG's default 128-bit LCG multiplier.
const PCG_MULT: u128 = (2_549_297_995_355_413_924_u128 << 64) | 4_865_540_595_714_422_341_u128;

/// `numpy.random.Generator(PCG64(SeedSequence(seed)))`, which is what gymnasium's
/// `np_random(seed)` builds.
///
/// PCG64 is PCG XSL-RR 128/64: a 128-bit LCG `state = state * MULT + inc` (stepped before
/// each output) whose 64-bit output is `rotr(hi ^ lo, state >> 122)`. numpy's bit generator
/// also buffers the unused high half of a 64-bit draw for the next 32-bit request.
#[derive(Clone, Debug)]
pub struct NumpyGenerator {
    state: u128,
    inc: u128,
    /// numpy's `has_uint32` / `uinteger`: the pending high half of a 64-bit draw.
    buffered_u32: Option<u32>,
}

impl NumpyGenerator {
    /// `Generator(PCG64(SeedSequence(seed)))`: `v = SeedSequence(seed).generate_state(4,
    /// np.uint64)` (see [`seed_sequence_words`] and [`seed_entropy_words`]), then numpy's
    /// `pcg64_set_seed(seed = v[0] << 64 | v[1], inc = v[2] << 64 | v[3])`, i.e. PCG's
    /// `srandom_r`: `inc = (inc << 1) | 1; state = 0; step; state += seed; step`. The 32-bit
    /// buffer starts empty.
    pub fn from_seed(seed: u64) -> Self {
        let w = seed_sequence_words(&seed_entropy_words(seed), 8);
        let word = |k: usize| -> u64 {
            let lo = w.get(2 * k).copied().unwrap_or(0);
            let hi = w.get(2 * k + 1).copied().unwrap_or(0);
            (u64::from(hi) << 32) | u64::from(lo)
        };
        let init_state = (u128::from(word(0)) << 64) | u128::from(word(1));
        let init_seq = (u128::from(word(2)) << 64) | u128::from(word(3));
        let mut g = Self {
            state: 0,
            inc: (init_seq << 1) | 1,
            buffered_u32: None,
        };
        g.step();
        g.state = g.state.wrapping_add(init_state);
        g.step();
        g
    }

    fn step(&mut self) {
        self.state = self.state.wrapping_mul(PCG_MULT).wrapping_add(self.inc);
    }

    /// The next 64-bit PCG64 output (numpy `pcg64_next64`, `PCG64.random_raw()`). Neither uses
    /// nor clears the buffered 32-bit half.
    pub fn next_u64(&mut self) -> u64 {
        self.step();
        let s = self.state;
        // Truncating casts: the high and low 64-bit halves, and the top 6 bits as the rotation.
        let xored = ((s >> 64) as u64) ^ (s as u64);
        xored.rotate_right((s >> 122) as u32)
    }

    /// The next 32-bit output (numpy `pcg64_next32`): the buffered high half if there is one,
    /// otherwise the low half of a fresh [`next_u64`](Self::next_u64), buffering its high half.
    pub fn next_u32(&mut self) -> u32 {
        if let Some(v) = self.buffered_u32.take() {
            return v;
        }
        let next = self.next_u64();
        self.buffered_u32 = Some((next >> 32) as u32);
        next as u32
    }

    /// `Generator.random()`: `(next_u64 >> 11) * 2**-53`, a double in `[0, 1)`.
    pub fn random_f64(&mut self) -> f64 {
        // A 53-bit integer converts to f64 exactly.
        (self.next_u64() >> 11) as f64 * (1.0 / 9_007_199_254_740_992.0)
    }

    /// `Generator.integers(low, high)` with the default `int64` dtype and `endpoint=False`:
    /// an integer in `[low, high)`.
    ///
    /// With `rng = high - 1 - low`: `rng == 0` returns `low` without drawing; `rng < 2**32 - 1`
    /// uses Lemire's method on (buffered) 32-bit draws (numpy
    /// `buffered_bounded_lemire_uint32`); `rng == 2**32 - 1` adds one raw 32-bit draw; wider
    /// ranges use Lemire's method on 64-bit draws (`bounded_lemire_uint64`).
    ///
    /// # Errors
    /// [`RngError::EmptyIntRange`] when `low >= high`.
    pub fn integers(&mut self, low: i64, high: i64) -> Result<i64, RngError> {
        bounded_i64(self, low, high, false)
    }

    /// `Generator.uniform(low, high)`: `low + (high - low) * random_f64()`, a double in
    /// `[low, high)` (up to rounding). `low == high` is allowed and still consumes a draw, as
    /// in numpy.
    ///
    /// # Errors
    /// [`RngError::UniformNotFinite`] when `high - low` is not finite (numpy's
    /// `OverflowError`), [`RngError::UniformReversed`] when `high < low`.
    pub fn uniform(&mut self, low: f64, high: f64) -> Result<f64, RngError> {
        let range = high - low;
        if !range.is_finite() {
            return Err(RngError::UniformNotFinite { low, high });
        }
        if range < 0.0 {
            return Err(RngError::UniformReversed { low, high });
        }
        Ok(low + range * self.random_f64())
    }
}

impl Words for NumpyGenerator {
    fn word32(&mut self) -> u32 {
        self.next_u32()
    }
    fn word64(&mut self) -> u64 {
        self.next_u64()
    }
}

// ---------------------------------------------------------------------------------------------
// PushT reset streams.
// ---------------------------------------------------------------------------------------------

/// Which stream a seeded PushT reset draws from.
///
/// Serialized (serde, [`FromStr`], [`Display`](fmt::Display)) as `"legacy"` / `"pcg64"`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ResetStream {
    /// Diffusion Policy and gym-pusht <= 0.1.5: `np.random.RandomState(seed)`. The default,
    /// since Diffusion Policy's test seeds 100000..100049 are defined with it.
    #[default]
    Legacy,
    /// gym-pusht >= 0.1.6: gymnasium's `np_random(seed)`, a PCG64 `Generator`.
    Pcg64,
}

impl ResetStream {
    /// Both streams, in declaration order.
    pub const ALL: [ResetStream; 2] = [ResetStream::Legacy, ResetStream::Pcg64];

    /// The name used by serde, [`FromStr`] and [`Display`](fmt::Display).
    pub fn as_str(self) -> &'static str {
        match self {
            ResetStream::Legacy => "legacy",
            ResetStream::Pcg64 => "pcg64",
        }
    }

    /// The five raw draws of a PushT reset for `seed`: `[agent_x, agent_y, block_x, block_y,
    /// block_angle]` (pixels, pixels, pixels, pixels, radians), exactly as numpy produces them.
    ///
    /// * `Legacy`: `rs = RandomState(seed)`; `randint(50, 450)` twice, `randint(100, 400)`
    ///   twice, then `randn() * 2 * pi - pi`, evaluated left to right (so the angle is a
    ///   scaled normal, not a uniform; Diffusion Policy's code, kept verbatim).
    /// * `Pcg64`: `g = Generator(PCG64(SeedSequence(seed)))`; `integers(50, 450)` twice,
    ///   `integers(100, 400)` twice, then `uniform(-pi, pi)`.
    ///
    /// # Errors
    /// [`RngError::LegacySeedOutOfRange`] for `Legacy` with `seed > u32::MAX` (numpy rejects
    /// such a `RandomState` seed). `Pcg64` accepts every `u64`.
    pub fn sample(self, seed: u64) -> Result<[f64; 5], RngError> {
        match self {
            ResetStream::Legacy => {
                let seed32 =
                    u32::try_from(seed).map_err(|_| RngError::LegacySeedOutOfRange { seed })?;
                let mut rs = LegacyRandomState::new(seed32);
                let ax = rs.randint(50, 450)?;
                let ay = rs.randint(50, 450)?;
                let bx = rs.randint(100, 400)?;
                let by = rs.randint(100, 400)?;
                let angle = rs.randn() * 2.0 * PI - PI;
                Ok([ax as f64, ay as f64, bx as f64, by as f64, angle])
            }
            ResetStream::Pcg64 => {
                let mut g = NumpyGenerator::from_seed(seed);
                let ax = g.integers(50, 450)?;
                let ay = g.integers(50, 450)?;
                let bx = g.integers(100, 400)?;
                let by = g.integers(100, 400)?;
                let angle = g.uniform(-PI, PI)?;
                Ok([ax as f64, ay as f64, bx as f64, by as f64, angle])
            }
        }
    }
}

/// A string that names no [`ResetStream`]; expected `"legacy"` or `"pcg64"`.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("unknown reset stream {input:?}: expected \"legacy\" or \"pcg64\"")]
pub struct ParseResetStreamError {
    /// The string that was given.
    pub input: String,
}

impl FromStr for ResetStream {
    type Err = ParseResetStreamError;

    /// Parses `"legacy"` or `"pcg64"` (exact, lower case, as serde writes them).
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        ResetStream::ALL
            .into_iter()
            .find(|r| r.as_str() == s)
            .ok_or_else(|| ParseResetStreamError {
                input: s.to_owned(),
            })
    }
}

impl fmt::Display for ResetStream {
    /// Writes `"legacy"` or `"pcg64"`.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde::Deserialize;

    // Floats in the fixture are strings holding Python's shortest round-trip repr, parsed with
    // `str::parse::<f64>` (correctly rounded); serde_json's default float parser is not
    // guaranteed to be (its `float_roundtrip` feature is off).
    const FIXTURE: &str = include_str!("../tests/fixtures/numpy_rng.json");

    #[derive(Deserialize)]
    struct Fixture {
        versions: Versions,
        draws_per_case: usize,
        legacy: Vec<LegacyCase>,
        pcg64: Vec<Pcg64Case>,
        seed_sequence: Vec<SeedSequenceCase>,
        reset: Resets,
    }

    #[derive(Deserialize)]
    struct Versions {
        numpy: String,
    }

    #[derive(Deserialize)]
    struct RangeCase {
        low: i64,
        high: i64,
        values: Vec<i64>,
    }

    #[derive(Deserialize)]
    struct MixedOp {
        op: String,
        value: String,
    }

    #[derive(Deserialize)]
    struct LegacyCase {
        seed: u32,
        u32: Vec<u32>,
        random_f64: Vec<String>,
        randn: Vec<String>,
        randint: Vec<RangeCase>,
        mixed: Vec<MixedOp>,
    }

    #[derive(Deserialize)]
    struct Pcg64Case {
        seed: u64,
        u64: Vec<u64>,
        u32: Vec<u32>,
        random_f64: Vec<String>,
        uniform: Vec<String>,
        integers: Vec<RangeCase>,
        mixed: Vec<MixedOp>,
    }

    #[derive(Deserialize)]
    struct SeedSequenceCase {
        /// A decimal string: the largest seeds exceed u128.
        seed: String,
        entropy: Vec<u32>,
        pool: Vec<u32>,
        words: Vec<u32>,
    }

    #[derive(Deserialize)]
    struct Resets {
        legacy: Vec<ResetCase>,
        pcg64: Vec<ResetCase>,
    }

    #[derive(Deserialize)]
    struct ResetCase {
        seed: u64,
        sample: Vec<String>,
    }

    fn fixture() -> Fixture {
        serde_json::from_str(FIXTURE).expect("fixture parses")
    }

    fn float(s: &str) -> f64 {
        s.parse::<f64>().expect("fixture float parses")
    }

    /// Bit-for-bit equality of a computed f64 with a fixture repr string.
    fn assert_bits(what: &str, got: f64, want: &str) {
        let want = float(want);
        assert_eq!(
            got.to_bits(),
            want.to_bits(),
            "{what}: got {got:?}, numpy {want:?}"
        );
    }

    /// Parses the `"int LOW HIGH"` / `"uniform LOW HIGH"` ops of the mixed sequences.
    fn op_args<T: FromStr>(op: &str) -> (T, T)
    where
        T::Err: fmt::Debug,
    {
        let mut it = op.split_whitespace().skip(1);
        let low = it.next().expect("low").parse().expect("low parses");
        let high = it.next().expect("high").parse().expect("high parses");
        (low, high)
    }

    #[test]
    fn fixture_is_from_numpy_2_2_6() {
        let fx = fixture();
        assert_eq!(fx.versions.numpy, "2.2.6");
        assert_eq!(fx.draws_per_case, 20);
        assert_eq!(fx.legacy.len(), 5);
        assert_eq!(fx.pcg64.len(), 6);
        assert_eq!(fx.reset.legacy.len(), 60);
        assert_eq!(fx.reset.pcg64.len(), 60);
    }

    #[test]
    fn legacy_raw_u32_matches_numpy() {
        for case in fixture().legacy {
            let mut rs = LegacyRandomState::new(case.seed);
            let got: Vec<u32> = (0..case.u32.len()).map(|_| rs.next_u32()).collect();
            assert_eq!(got, case.u32, "seed {}", case.seed);
        }
    }

    #[test]
    fn legacy_u32_across_key_regeneration() {
        // Known MT19937 values (init_genrand(5489), the reference implementation's default
        // seed): the 1st and the 10000th output.
        let mut rs = LegacyRandomState::new(5489);
        assert_eq!(rs.next_u32(), 3_499_211_612);
        for _ in 1..9999 {
            rs.next_u32();
        }
        assert_eq!(rs.next_u32(), 4_123_659_995);
    }

    #[test]
    fn legacy_random_f64_matches_numpy() {
        for case in fixture().legacy {
            let mut rs = LegacyRandomState::new(case.seed);
            for (i, want) in case.random_f64.iter().enumerate() {
                assert_bits(
                    &format!("seed {} draw {i}", case.seed),
                    rs.random_f64(),
                    want,
                );
            }
        }
    }

    #[test]
    fn legacy_randn_matches_numpy() {
        // Exact: `ln` and `sqrt` resolve to the same glibc/IEEE routines numpy uses; no ulp
        // tolerance was needed.
        for case in fixture().legacy {
            let mut rs = LegacyRandomState::new(case.seed);
            for (i, want) in case.randn.iter().enumerate() {
                assert_bits(&format!("seed {} randn {i}", case.seed), rs.randn(), want);
            }
        }
    }

    #[test]
    fn legacy_randint_matches_numpy() {
        for case in fixture().legacy {
            assert_eq!(case.randint.len(), 7);
            for r in &case.randint {
                let mut rs = LegacyRandomState::new(case.seed);
                let got: Vec<i64> = (0..r.values.len())
                    .map(|_| rs.randint(r.low, r.high).expect("valid range"))
                    .collect();
                assert_eq!(
                    got, r.values,
                    "seed {} randint({}, {})",
                    case.seed, r.low, r.high
                );
            }
        }
    }

    #[test]
    fn legacy_interleaved_calls_match_numpy() {
        for case in fixture().legacy {
            let mut rs = LegacyRandomState::new(case.seed);
            for (i, m) in case.mixed.iter().enumerate() {
                let what = format!("seed {} mixed op {i} ({})", case.seed, m.op);
                match m.op.split_whitespace().next() {
                    Some("randn") => assert_bits(&what, rs.randn(), &m.value),
                    Some("f64") => assert_bits(&what, rs.random_f64(), &m.value),
                    Some("u32") => {
                        assert_eq!(rs.next_u32().to_string(), m.value, "{what}");
                    }
                    Some("int") => {
                        let (low, high) = op_args::<i64>(&m.op);
                        let got = rs.randint(low, high).expect("valid range");
                        assert_eq!(got.to_string(), m.value, "{what}");
                    }
                    other => panic!("unknown op {other:?}"),
                }
            }
        }
    }

    #[test]
    fn pcg64_raw_u64_and_u32_match_numpy() {
        for case in fixture().pcg64 {
            let mut g = NumpyGenerator::from_seed(case.seed);
            let got: Vec<u64> = (0..case.u64.len()).map(|_| g.next_u64()).collect();
            assert_eq!(got, case.u64, "seed {} u64", case.seed);
            let mut g = NumpyGenerator::from_seed(case.seed);
            let got: Vec<u32> = (0..case.u32.len()).map(|_| g.next_u32()).collect();
            assert_eq!(got, case.u32, "seed {} u32", case.seed);
        }
    }

    #[test]
    fn pcg64_random_f64_and_uniform_match_numpy() {
        for case in fixture().pcg64 {
            let mut g = NumpyGenerator::from_seed(case.seed);
            for (i, want) in case.random_f64.iter().enumerate() {
                assert_bits(
                    &format!("seed {} random {i}", case.seed),
                    g.random_f64(),
                    want,
                );
            }
            let mut g = NumpyGenerator::from_seed(case.seed);
            for (i, want) in case.uniform.iter().enumerate() {
                let got = g.uniform(-PI, PI).expect("valid range");
                assert_bits(&format!("seed {} uniform {i}", case.seed), got, want);
            }
        }
    }

    #[test]
    fn pcg64_integers_match_numpy() {
        for case in fixture().pcg64 {
            assert_eq!(case.integers.len(), 7);
            for r in &case.integers {
                let mut g = NumpyGenerator::from_seed(case.seed);
                let got: Vec<i64> = (0..r.values.len())
                    .map(|_| g.integers(r.low, r.high).expect("valid range"))
                    .collect();
                assert_eq!(
                    got, r.values,
                    "seed {} integers({}, {})",
                    case.seed, r.low, r.high
                );
            }
        }
    }

    #[test]
    fn pcg64_interleaved_calls_match_numpy() {
        for case in fixture().pcg64 {
            let mut g = NumpyGenerator::from_seed(case.seed);
            for (i, m) in case.mixed.iter().enumerate() {
                let what = format!("seed {} mixed op {i} ({})", case.seed, m.op);
                match m.op.split_whitespace().next() {
                    Some("u32") => assert_eq!(g.next_u32().to_string(), m.value, "{what}"),
                    Some("u64") => assert_eq!(g.next_u64().to_string(), m.value, "{what}"),
                    Some("f64") => assert_bits(&what, g.random_f64(), &m.value),
                    Some("int") => {
                        let (low, high) = op_args::<i64>(&m.op);
                        let got = g.integers(low, high).expect("valid range");
                        assert_eq!(got.to_string(), m.value, "{what}");
                    }
                    Some("uniform") => {
                        let (low, high) = op_args::<f64>(&m.op);
                        let got = g.uniform(low, high).expect("valid range");
                        assert_bits(&what, got, &m.value);
                    }
                    other => panic!("unknown op {other:?}"),
                }
            }
        }
    }

    /// Entropy words of an arbitrary-size non-negative integer (numpy's
    /// `_coerce_to_uint32_array`), for the fixture's seeds beyond u64.
    fn entropy_of(mut n: u128) -> Vec<u32> {
        let mut out = vec![];
        loop {
            out.push(n as u32);
            n >>= 32;
            if n == 0 {
                return out;
            }
        }
    }

    #[test]
    fn seed_sequence_matches_numpy() {
        let fx = fixture();
        assert!(fx.seed_sequence.iter().any(|c| c.entropy.len() > 4));
        for case in fx.seed_sequence {
            if let Ok(s) = case.seed.parse::<u128>() {
                assert_eq!(entropy_of(s), case.entropy, "seed {s}");
            }
            if let Ok(s) = case.seed.parse::<u64>() {
                assert_eq!(seed_entropy_words(s), case.entropy, "seed {s}");
            }
            let words = seed_sequence_words(&case.entropy, case.words.len());
            assert_eq!(words, case.words, "seed {}", case.seed);
            // A longer request extends the same cycle; a shorter one is a prefix.
            let long = seed_sequence_words(&case.entropy, 13);
            assert_eq!(&long[..8], &case.words[..]);
            assert_eq!(seed_sequence_words(&case.entropy, 3), &case.words[..3]);
            assert_eq!(seed_sequence_pool(&case.entropy), &case.pool[..]);
        }
        assert!(seed_sequence_words(&[1, 2], 0).is_empty());
        // Empty entropy does not panic (numpy never produces it from an integer).
        assert_eq!(seed_sequence_words(&[], 5).len(), 5);
    }

    #[test]
    fn reset_samples_match_numpy() {
        let fx = fixture();
        for (stream, cases) in [
            (ResetStream::Legacy, &fx.reset.legacy),
            (ResetStream::Pcg64, &fx.reset.pcg64),
        ] {
            for case in cases {
                let got = stream.sample(case.seed).expect("valid seed");
                assert_eq!(case.sample.len(), 5);
                for (k, (g, w)) in got.iter().zip(&case.sample).enumerate() {
                    assert_bits(&format!("{stream} seed {} draw {k}", case.seed), *g, w);
                }
            }
        }
    }

    #[test]
    fn gym_pusht_seed_0_anchor() {
        // gym-pusht 0.1.8 reset(seed=0) puts the agent at (390, 304).
        let s = ResetStream::Pcg64.sample(0).expect("valid seed");
        assert_eq!(&s[..2], &[390.0, 304.0]);
        assert!((100.0..400.0).contains(&s[2]) && (100.0..400.0).contains(&s[3]));
        assert!((-PI..PI).contains(&s[4]));
    }

    #[test]
    fn empty_integer_ranges_are_errors() {
        let mut rs = LegacyRandomState::new(0);
        let mut g = NumpyGenerator::from_seed(0);
        for (low, high) in [(5, 5), (6, 5), (i64::MAX, i64::MIN), (0, -1)] {
            let want = RngError::EmptyIntRange { low, high };
            assert_eq!(rs.randint(low, high), Err(want.clone()));
            assert_eq!(g.integers(low, high), Err(want));
        }
        let msg = RngError::EmptyIntRange { low: 7, high: 3 }.to_string();
        assert!(msg.contains('7') && msg.contains('3'), "{msg}");
        // A rejected call draws nothing.
        assert_eq!(rs.next_u32(), LegacyRandomState::new(0).next_u32());
        assert_eq!(g.next_u64(), NumpyGenerator::from_seed(0).next_u64());
    }

    #[test]
    fn extreme_integer_ranges_stay_in_range() {
        let mut rs = LegacyRandomState::new(3);
        let mut g = NumpyGenerator::from_seed(3);
        for (low, high) in [
            (i64::MIN, i64::MAX),
            (i64::MIN, i64::MIN + 1),
            (i64::MAX - 1, i64::MAX),
            (i64::MIN, 0),
            (-1, i64::MAX),
            (0, 1 << 32),
            (-(1 << 31), 1 << 31),
            (0, (1 << 32) + 1),
        ] {
            for _ in 0..50 {
                let a = rs.randint(low, high).expect("valid range");
                let b = g.integers(low, high).expect("valid range");
                assert!(low <= a && a < high, "{a} not in [{low}, {high})");
                assert!(low <= b && b < high, "{b} not in [{low}, {high})");
            }
        }
    }

    #[test]
    fn bad_uniform_ranges_are_errors() {
        let mut g = NumpyGenerator::from_seed(0);
        for (low, high) in [
            (0.0, f64::INFINITY),
            (f64::NEG_INFINITY, 0.0),
            (f64::NAN, 1.0),
            (0.0, f64::NAN),
            (-1e308, 1e308),
        ] {
            match g.uniform(low, high) {
                Err(RngError::UniformNotFinite { .. }) => {}
                other => panic!("uniform({low}, {high}) gave {other:?}"),
            }
        }
        assert_eq!(
            g.uniform(1.0, 0.0),
            Err(RngError::UniformReversed {
                low: 1.0,
                high: 0.0
            })
        );
        let msg = RngError::UniformReversed {
            low: 1.5,
            high: -2.5,
        }
        .to_string();
        assert!(msg.contains("1.5") && msg.contains("-2.5"), "{msg}");
        assert_eq!(g.next_u64(), NumpyGenerator::from_seed(0).next_u64());
        assert_eq!(g.uniform(2.5, 2.5), Ok(2.5));
    }

    #[test]
    fn legacy_seed_above_u32_is_an_error() {
        let seed = u64::from(u32::MAX) + 1;
        assert_eq!(
            ResetStream::Legacy.sample(seed),
            Err(RngError::LegacySeedOutOfRange { seed })
        );
        assert!(ResetStream::Legacy.sample(u64::from(u32::MAX)).is_ok());
        assert!(ResetStream::Pcg64.sample(u64::MAX).is_ok());
        assert!(
            RngError::LegacySeedOutOfRange { seed }
                .to_string()
                .contains("4294967296")
        );
    }

    #[test]
    fn reset_stream_names_round_trip() {
        assert_eq!(ResetStream::default(), ResetStream::Legacy);
        for s in ResetStream::ALL {
            assert_eq!(s.to_string().parse::<ResetStream>(), Ok(s));
            let json = serde_json::to_string(&s).expect("serializes");
            assert_eq!(json, format!("\"{s}\""));
            assert_eq!(
                serde_json::from_str::<ResetStream>(&json).expect("deserializes"),
                s
            );
        }
        assert_eq!(ResetStream::Pcg64.to_string(), "pcg64");
        let err = "PCG64".parse::<ResetStream>().expect_err("case-sensitive");
        assert_eq!(
            err,
            ParseResetStreamError {
                input: "PCG64".to_owned()
            }
        );
        assert!(err.to_string().contains("PCG64"));
        assert!("".parse::<ResetStream>().is_err());
    }
}
