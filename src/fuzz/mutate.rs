//! The mutator of the fuzz runs: from a valid seed file, a broken one, deterministically from an
//! injected seeded RNG (same seed, same inputs: a finding is reproduced by its index).
//!
//! Byte-level changes (bit flips, byte insert/delete, truncation, repeated chunks, integers and
//! floats overwritten with extreme values, mostly near the start where headers are) and, for text
//! formats, token- and line-level ones (a number replaced by a huge count, NaN, inf, a negative or
//! a word; lines duplicated, deleted, swapped).

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Integers that break counts and sizes: zero, sign and width boundaries, 10^12.
const INTERESTING_INTEGERS: [u64; 12] = [
    0,
    1,
    0x7f,
    0xff,
    0x7fff,
    0xffff,
    0x7fff_ffff,
    0x8000_0000,
    0xffff_ffff,
    1_000_000_000_000,
    0x7fff_ffff_ffff_ffff,
    u64::MAX,
];

/// Floats that break geometry: NaN, infinities, extremes, negative zero.
const INTERESTING_FLOATS: [f64; 9] = [
    f64::NAN,
    f64::INFINITY,
    f64::NEG_INFINITY,
    f64::MAX,
    f64::MIN_POSITIVE,
    -0.0,
    1e30,
    -1.0,
    0.0,
];

/// Replacements of a number in a text format: huge counts, non-finite values, wrong types.
const INTERESTING_TOKENS: [&str; 20] = [
    "1000000000000",
    "18446744073709551616",
    "4294967295",
    "2147483648",
    "-1",
    "0",
    "nan",
    "NaN",
    "inf",
    "-inf",
    "1e309",
    "-1e309",
    "abc",
    "",
    "0x10",
    "1.5",
    "99999999999999999999999999",
    "1e-320",
    "\u{fffd}",
    "\"",
];

/// A deterministic mutator (ChaCha8, seeded by the caller).
pub struct Mutator {
    rng: ChaCha8Rng,
}

impl Mutator {
    pub fn new(seed: u64) -> Self {
        Self {
            rng: ChaCha8Rng::seed_from_u64(seed),
        }
    }

    /// One broken input: 1 to 4 changes of `seed_input`. `text`: the format is (partly) text, so
    /// token and line changes are used too.
    pub fn mutate(&mut self, seed_input: &[u8], text: bool) -> Vec<u8> {
        let mut data = seed_input.to_vec();
        let changes = self.rng.random_range(1..=4);
        for _ in 0..changes {
            if text && self.rng.random_bool(0.5) {
                self.text_change(&mut data);
            } else {
                self.byte_change(&mut data);
            }
        }
        data
    }

    /// An offset in `0..len`, half the time in the first 128 bytes (headers).
    fn offset(&mut self, len: usize) -> usize {
        if len == 0 {
            return 0;
        }
        if self.rng.random_bool(0.5) {
            self.rng.random_range(0..len.min(128))
        } else {
            self.rng.random_range(0..len)
        }
    }

    fn byte_change(&mut self, data: &mut Vec<u8>) {
        let len = data.len();
        match self.rng.random_range(0..9) {
            0 if len > 0 => {
                // Flip 1 to 8 bits.
                for _ in 0..self.rng.random_range(1..=8) {
                    let at = self.offset(len);
                    data[at] ^= 1 << self.rng.random_range(0..8);
                }
            }
            1 if len > 0 => {
                let at = self.offset(len);
                data[at] =
                    [0x00, 0xff, 0x7f, 0x80, b'\n', b' ', b'-', b'9'][self.rng.random_range(0..8)];
            }
            2 => {
                let at = self.rng.random_range(0..=len);
                let count = self.rng.random_range(1..=16);
                let bytes: Vec<u8> = (0..count).map(|_| self.rng.random()).collect();
                data.splice(at..at, bytes);
            }
            3 if len > 0 => {
                let at = self.offset(len);
                let count = self.rng.random_range(1..=16.min(len - at).max(1));
                data.drain(at..(at + count).min(len));
            }
            4 => {
                // Truncation: anywhere, often within the header.
                let at = self.offset(len);
                data.truncate(at);
            }
            5 if len > 0 => {
                // A chunk repeated in place.
                let at = self.rng.random_range(0..len);
                let count = self.rng.random_range(1..=64.min(len - at));
                let chunk = data[at..at + count].to_vec();
                data.splice(at..at, chunk);
            }
            6 | 7 if len > 0 => {
                // An integer overwritten (u8/u16/u32/u64, either byte order).
                let value =
                    INTERESTING_INTEGERS[self.rng.random_range(0..INTERESTING_INTEGERS.len())];
                let width = [1usize, 2, 4, 8][self.rng.random_range(0..4)];
                let big_endian = self.rng.random_bool(0.3);
                let bytes = value.to_le_bytes();
                let mut field = bytes[..width].to_vec();
                if big_endian {
                    field.reverse();
                }
                self.overwrite(data, &field);
            }
            8 if len > 0 => {
                let value = INTERESTING_FLOATS[self.rng.random_range(0..INTERESTING_FLOATS.len())];
                let field = if self.rng.random_bool(0.5) {
                    (value as f32).to_le_bytes().to_vec()
                } else {
                    value.to_le_bytes().to_vec()
                };
                self.overwrite(data, &field);
            }
            _ => {
                // Empty input: give it a byte to work on.
                data.push(self.rng.random());
            }
        }
    }

    fn overwrite(&mut self, data: &mut [u8], field: &[u8]) {
        if data.len() < field.len() {
            return;
        }
        let at = self.offset(data.len() - field.len() + 1);
        data[at..at + field.len()].copy_from_slice(field);
    }

    fn text_change(&mut self, data: &mut Vec<u8>) {
        match self.rng.random_range(0..5) {
            0 | 1 => self.replace_number(data),
            choice => {
                let mut lines: Vec<Vec<u8>> = data
                    .split_inclusive(|&byte| byte == b'\n')
                    .map(<[u8]>::to_vec)
                    .collect();
                if lines.is_empty() {
                    return;
                }
                let a = self.rng.random_range(0..lines.len());
                let b = self.rng.random_range(0..lines.len());
                match choice {
                    2 => {
                        let line = lines[a].clone();
                        lines.insert(b, line);
                    }
                    3 => {
                        lines.remove(a);
                    }
                    _ => lines.swap(a, b),
                }
                *data = lines.concat();
            }
        }
    }

    /// Replaces one number (a run of digits with its sign, dot and exponent) by an interesting
    /// token; a random position when there is no number.
    fn replace_number(&mut self, data: &mut Vec<u8>) {
        let is_number_byte =
            |byte: u8| byte.is_ascii_digit() || matches!(byte, b'.' | b'-' | b'+' | b'e' | b'E');
        let mut numbers = Vec::new();
        let mut index = 0;
        while index < data.len() {
            if data[index].is_ascii_digit() {
                let mut start = index;
                while start > 0 && is_number_byte(data[start - 1]) {
                    start -= 1;
                }
                let mut end = index;
                while end < data.len() && is_number_byte(data[end]) {
                    end += 1;
                }
                numbers.push((start, end));
                index = end;
            } else {
                index += 1;
            }
        }
        let token =
            INTERESTING_TOKENS[self.rng.random_range(0..INTERESTING_TOKENS.len())].as_bytes();
        if numbers.is_empty() {
            let at = self.rng.random_range(0..=data.len());
            data.splice(at..at, token.iter().copied());
            return;
        }
        // Numbers near the start (header counts) are picked as often as all the others.
        let pick = if self.rng.random_bool(0.5) {
            self.rng.random_range(0..numbers.len().min(16))
        } else {
            self.rng.random_range(0..numbers.len())
        };
        let (start, end) = numbers[pick];
        data.splice(start..end, token.iter().copied());
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn same_seed_same_inputs_and_every_input_differs_from_the_seed_often() {
        let seed_input =
            b"ply\nformat ascii 1.0\nelement vertex 3\nend_header\n0 0 0\n1 0 0\n0 1 0\n";
        let first: Vec<Vec<u8>> = {
            let mut mutator = Mutator::new(7);
            (0..200).map(|_| mutator.mutate(seed_input, true)).collect()
        };
        let second: Vec<Vec<u8>> = {
            let mut mutator = Mutator::new(7);
            (0..200).map(|_| mutator.mutate(seed_input, true)).collect()
        };
        assert_eq!(first, second);
        let changed = first
            .iter()
            .filter(|input| input.as_slice() != seed_input)
            .count();
        assert!(
            changed > 180,
            "only {changed} of 200 inputs differ from the seed"
        );
        // Huge counts do appear in headers.
        assert!(first
            .iter()
            .any(|input| input.windows(13).any(|window| window == b"1000000000000")));
    }
}
