//! 16-bit Huffman compression and decompression.
//! Huffman compression and decompression routines written
//!    by Christian Rouet for his PIZ image file format.
// see https://github.com/AcademySoftwareFoundation/openexr/blob/88246d991e0318c043e6f584f7493da08a31f9f8/OpenEXR/IlmImf/ImfHuf.cpp

use std::{
    cmp::Ordering,
    collections::BinaryHeap,
    convert::{TryFrom, TryInto},
    io::{Cursor, Read},
};

use crate::{
    error::{u64_to_usize, Error, Result, UnitResult},
    io::Data,
    math::RoundingMode,
};

pub fn decompress(compressed: &[u8], expected_size: usize) -> Result<Vec<u16>> {
    let mut remaining_compressed = compressed;

    let min_code_index = usize::try_from(u32::read_le(&mut remaining_compressed)?)?;
    let max_code_index_32 = u32::read_le(&mut remaining_compressed)?;
    let _table_size = usize::try_from(u32::read_le(&mut remaining_compressed)?)?; // TODO check this and return Err?
    let bit_count = usize::try_from(u32::read_le(&mut remaining_compressed)?)?;
    let _skipped = u32::read_le(&mut remaining_compressed)?; // what is this

    let max_code_index = usize::try_from(max_code_index_32)?;
    // A table of no symbol (smallest above largest) no encoder writes: the
    // code lengths are kept only up to the largest symbol.
    if min_code_index >= ENCODING_TABLE_SIZE
        || max_code_index >= ENCODING_TABLE_SIZE
        || min_code_index > max_code_index
    {
        return Err(Error::invalid(INVALID_TABLE_SIZE));
    }

    if RoundingMode::Up.divide(bit_count, 8) > remaining_compressed.len() {
        return Err(Error::invalid(NOT_ENOUGH_DATA));
    }

    let code_lengths =
        read_code_lengths(&mut remaining_compressed, min_code_index, max_code_index)?;
    if bit_count > 8 * remaining_compressed.len() {
        return Err(Error::invalid(INVALID_BIT_COUNT));
    }

    let decoding_table = build_decoding_table(&code_lengths, min_code_index, max_code_index_32)?;

    let result = decode_with_tables(
        &decoding_table,
        remaining_compressed,
        bit_count,
        max_code_index_32,
        expected_size,
    )?;

    Ok(result)
}

pub fn compress(uncompressed: &[u16]) -> Result<Vec<u8>> {
    if uncompressed.is_empty() {
        return Ok(vec![]);
    }

    compress_with_frequencies(uncompressed, count_frequencies(uncompressed))
}

/// Encodes with the codes of these symbol frequencies (every symbol of the
/// data must have one).
fn compress_with_frequencies(uncompressed: &[u16], mut frequencies: Vec<u64>) -> Result<Vec<u8>> {
    let (min_code_index, max_code_index) = build_encoding_table(&mut frequencies)?;

    // The header's five numbers come last, once the data's lengths are known.
    const HEADER_SIZE: usize = 5 * std::mem::size_of::<u32>();
    let mut out = Vec::with_capacity(uncompressed.len() + HEADER_SIZE);
    out.resize(HEADER_SIZE, 0);

    let table_start = out.len();
    pack_encoding_table(&frequencies, min_code_index, max_code_index, &mut out);

    let data_start = out.len();
    let bit_count = encode_with_frequencies(&frequencies, uncompressed, max_code_index, &mut out);

    let mut result = Cursor::new(out);
    let table_length = data_start - table_start;

    u32::try_from(min_code_index)?.write_le(&mut result)?;
    u32::try_from(max_code_index)?.write_le(&mut result)?;
    u32::try_from(table_length)?.write_le(&mut result)?;
    u32::try_from(bit_count)?.write_le(&mut result)?;
    0_u32.write_le(&mut result)?;

    Ok(result.into_inner())
}

const ENCODE_BITS: u64 = 16; // literal (value) bit length
const MAX_CODE_LENGTH: usize = 58;

const ENCODING_TABLE_SIZE: usize = ((1 << ENCODE_BITS) + 1) as usize;

const SHORT_ZEROCODE_RUN: u64 = 59;
const LONG_ZEROCODE_RUN: u64 = 63;
const SHORTEST_LONG_RUN: u64 = 2 + LONG_ZEROCODE_RUN - SHORT_ZEROCODE_RUN;
const LONGEST_LONG_RUN: u64 = 255 + SHORTEST_LONG_RUN;

/// How many bits of the stream the primary decoding table resolves at once.
/// 2¹² eight-byte entries (32 KB) stay in the first-level cache.
const PRIMARY_BITS: u32 = 12;

/// The decoding table. Codes of at most `PRIMARY_BITS` bits are resolved by one
/// look-up of the stream's next `PRIMARY_BITS` bits. Longer codes are found by
/// their length: the codes are canonical (`build_canonical_table`), so the codes
/// of one length are consecutive numbers, assigned in the order of their symbols.
struct DecodingTable {
    /// Per prefix: the short code it starts with (`FIRST_*`, or 0), and the
    /// short code that follows within the prefix (`BOTH_*`, or 0), when
    /// neither is the run code and both symbols are `u16`s.
    primary: Vec<u64>,
    /// Per code length: the lowest code of that length, how many codes have it,
    /// and where their symbols start in `long_symbols` (lengths ≤ `PRIMARY_BITS`
    /// are empty).
    long_lengths: Vec<LongCodes>,
    long_symbols: Vec<u32>,
}

/// A `primary` entry: the first code's length (the low byte) and symbol, the
/// length of the first two codes together (the next byte) and the second's
/// symbol.
const LENGTH_MASK: u64 = 0xFF;
const FIRST_SYMBOL_SHIFT: u32 = 16;
const SYMBOL_MASK: u64 = 0x1_FFFF;
const BOTH_LENGTH_SHIFT: u32 = 8;
const SECOND_SYMBOL_SHIFT: u32 = 33;

#[derive(Clone, Copy, Default)]
struct LongCodes {
    first_code: u64,
    count: u64,
    first_symbol: usize,
}

impl DecodingTable {
    /// The symbol of the code longer than `PRIMARY_BITS` that the stream starts with.
    #[inline(never)]
    fn decode_long(&self, bits: &mut BitReader<'_>) -> Result<u32> {
        bits.refill();
        for (length, codes) in self.long_lengths.iter().enumerate().skip(PRIMARY_BITS as usize + 1)
        {
            let length = length as u32;
            if codes.count == 0 {
                continue;
            }
            if length as usize > bits.remaining {
                break;
            }
            let offset = bits.peek_any(length).wrapping_sub(codes.first_code);
            if offset < codes.count {
                bits.consume_any(length);
                return Ok(self.long_symbols[codes.first_symbol + offset as usize]);
            }
        }
        Err(Error::invalid(INVALID_CODE))
    }
}

/// Reads the bit stream most significant bit first, `bit_count` bits in all.
struct BitReader<'a> {
    input: &'a [u8],
    /// The first byte of `input` that `bits` has not taken yet.
    next_byte: usize,
    /// Left-aligned: the stream's next `available` bits, then zeros or the
    /// stream's bits after them.
    bits: u64,
    available: u32,
    /// The stream's bits not consumed yet.
    remaining: usize,
}

impl<'a> BitReader<'a> {
    fn new(input: &'a [u8], bit_count: usize) -> Result<Self> {
        let input =
            input.get(..(bit_count + 7) / 8).ok_or_else(|| Error::invalid(INVALID_BIT_COUNT))?;
        let mut reader = BitReader {
            input,
            next_byte: 0,
            bits: 0,
            available: 0,
            remaining: bit_count,
        };
        reader.refill();
        Ok(reader)
    }

    /// Takes bytes until at least 56 bits are available, or the input ends.
    #[inline]
    fn refill(&mut self) {
        if let Some(bytes) = self.input.get(self.next_byte..self.next_byte + 8) {
            // Also puts the bits beyond the whole bytes taken in place; a later
            // refill puts the same bits there again.
            let word = u64::from_be_bytes(bytes.try_into().unwrap());
            self.bits |= word >> self.available;
            let taken = (63 - self.available) >> 3;
            self.next_byte += taken as usize;
            self.available += taken * 8;
        } else {
            while self.available <= 56 {
                match self.input.get(self.next_byte) {
                    Some(&byte) => {
                        self.bits |= u64::from(byte) << (56 - self.available);
                        self.next_byte += 1;
                        self.available += 8;
                    }
                    None => break,
                }
            }
        }
    }

    /// The next `count` (1 ..= `available`) bits.
    #[inline]
    fn peek(&self, count: u32) -> u64 {
        self.bits >> (64 - count)
    }

    /// Moves past `count` (≤ `available`) bits.
    #[inline]
    fn consume(&mut self, count: u32) -> UnitResult {
        if count as usize > self.remaining {
            return Err(Error::invalid(INVALID_CODE));
        }
        self.bits <<= count;
        self.available -= count;
        self.remaining -= count as usize;
        Ok(())
    }

    /// The next `count` (1 ..= 64, ≤ `remaining`) bits, however many are available.
    fn peek_any(&self, count: u32) -> u64 {
        if count <= self.available {
            return self.peek(count);
        }
        let position = self.next_byte * 8 - self.available as usize;
        let mut padded = [0_u8; 16];
        let tail = &self.input[position / 8..];
        let taken = tail.len().min(16);
        padded[..taken].copy_from_slice(&tail[..taken]);
        ((u128::from_be_bytes(padded) << (position % 8)) >> (128 - count)) as u64
    }

    /// Moves past `count` (≤ `remaining`) bits, however many are available.
    fn consume_any(&mut self, count: u32) {
        let position = self.next_byte * 8 - self.available as usize + count as usize;
        self.remaining -= count as usize;
        self.next_byte = position / 8;
        self.bits = 0;
        self.available = 0;
        self.refill();
        let skipped = (position % 8) as u32;
        self.bits <<= skipped;
        self.available -= skipped;
    }
}

/// Decode (uncompress) the bit stream with the decoding table.
fn decode_with_tables(
    decoding_table: &DecodingTable,
    input: &[u8],
    input_bit_count: usize,
    run_length_code: u32,
    expected_output_size: usize,
) -> Result<Vec<u16>> {
    let mut output = Vec::with_capacity(expected_output_size);
    let mut bits = BitReader::new(input, input_bit_count)?;

    while bits.remaining > 0 {
        // A short code and a run's count take at most 20 bits.
        if bits.available < PRIMARY_BITS + 8 {
            bits.refill();
        }
        let entry = decoding_table.primary[bits.peek(PRIMARY_BITS) as usize];

        // Two short codes at once (neither a run), where the stream has both.
        let both_length = ((entry >> BOTH_LENGTH_SHIFT) & LENGTH_MASK) as u32;
        if both_length != 0 && both_length as usize <= bits.remaining {
            if output.len() + 2 > expected_output_size {
                return Err(Error::invalid(TOO_MUCH_DATA));
            }
            bits.consume(both_length)?;
            output.push((entry >> FIRST_SYMBOL_SHIFT) as u16);
            output.push((entry >> SECOND_SYMBOL_SHIFT) as u16);
            continue;
        }

        let symbol = if entry != 0 {
            bits.consume((entry & LENGTH_MASK) as u32)?;
            ((entry >> FIRST_SYMBOL_SHIFT) & SYMBOL_MASK) as u32
        } else {
            decoding_table.decode_long(&mut bits)?
        };

        if symbol == run_length_code {
            if bits.available < 8 {
                bits.refill();
            }
            if bits.remaining < 8 {
                return Err(Error::invalid(NOT_ENOUGH_DATA));
            }
            let repetitions = bits.peek(8) as usize;
            bits.consume(8)?;

            let repeated = *output.last().ok_or_else(|| Error::invalid(NOT_ENOUGH_DATA))?;
            if output.len() + repetitions > expected_output_size {
                return Err(Error::invalid(TOO_MUCH_DATA));
            }
            output.extend(std::iter::repeat(repeated).take(repetitions));
        } else if output.len() < expected_output_size {
            output.push(u16::try_from(symbol)?);
        } else {
            return Err(Error::invalid(TOO_MUCH_DATA));
        }
    }

    if output.len() != expected_output_size {
        return Err(Error::invalid(NOT_ENOUGH_DATA));
    }

    Ok(output)
}

/// Build the decoding table from the symbols' code lengths, with the codes
/// that `build_canonical_table` assigns to them.
fn build_decoding_table(
    code_lengths: &[u8],
    min_code_index: usize,
    run_length_code: u32,
) -> Result<DecodingTable> {
    let mut count_per_length = [0_u64; MAX_CODE_LENGTH + 1];
    for &length in code_lengths[min_code_index..].iter().filter(|&&length| length != 0) {
        count_per_length[usize::from(length)] += 1;
    }
    let mut next_code = first_code_per_length(&count_per_length);

    let mut long_lengths = vec![LongCodes::default(); MAX_CODE_LENGTH + 1];
    let mut long_code_count = 0;
    for (length, (&count, &first_code)) in count_per_length.iter().zip(&next_code).enumerate() {
        // The codes of one length are consecutive: the last must fit too.
        if count != 0 && (first_code + count - 1) >> length != 0 {
            return Err(Error::invalid(INVALID_TABLE_ENTRY));
        }
        if length > PRIMARY_BITS as usize {
            long_lengths[length] = LongCodes {
                first_code,
                count,
                first_symbol: long_code_count,
            };
            long_code_count += u64_to_usize(count, "long code count")?;
        }
    }

    // Per prefix, `symbol << 8 | length` of the short code it starts with.
    let mut short_codes = vec![0_u32; 1 << PRIMARY_BITS];
    let mut long_symbols = vec![0_u32; long_code_count];
    for (symbol, &length) in code_lengths.iter().enumerate().skip(min_code_index) {
        let length = usize::from(length);
        if length == 0 {
            continue;
        }
        let symbol = u32::try_from(symbol)?;
        let code = next_code[length];
        next_code[length] += 1;

        if length > PRIMARY_BITS as usize {
            let codes = &long_lengths[length];
            long_symbols[codes.first_symbol + (code - codes.first_code) as usize] = symbol;
        } else {
            let unused_bits = PRIMARY_BITS as usize - length;
            let start = (code as usize) << unused_bits;
            short_codes[start..start + (1 << unused_bits)].fill((symbol << 8) | length as u32);
        }
    }

    let pairable = |symbol: u32| symbol != run_length_code && symbol <= u32::from(u16::MAX);
    let primary = short_codes
        .iter()
        .enumerate()
        .map(|(prefix, &first)| {
            let (first_length, first_symbol) = (first & 0xFF, first >> 8);
            let mut entry =
                (u64::from(first_symbol) << FIRST_SYMBOL_SHIFT) | u64::from(first_length);
            if first != 0 && first_length < PRIMARY_BITS && pairable(first_symbol) {
                // The prefix's bits after the first code: the second code is
                // known if it ends within them.
                let second = short_codes[(prefix << first_length) & ((1 << PRIMARY_BITS) - 1)];
                let (second_length, second_symbol) = (second & 0xFF, second >> 8);
                if second != 0
                    && first_length + second_length <= PRIMARY_BITS
                    && pairable(second_symbol)
                {
                    entry |= (u64::from(first_length + second_length) << BOTH_LENGTH_SHIFT)
                        | (u64::from(second_symbol) << SECOND_SYMBOL_SHIFT);
                }
            }
            entry
        })
        .collect();

    Ok(DecodingTable {
        primary,
        long_lengths,
        long_symbols,
    })
}

/// Run-length-decompresses all zero runs from the packed table to the code
/// length of every symbol up to `max_code_index` (those below `min_code_index`
/// have none).
fn read_code_lengths(
    packed: &mut impl Read,
    min_code_index: usize,
    max_code_index: usize,
) -> Result<Vec<u8>> {
    let mut code_bits = 0_u64;
    let mut code_bit_count = 0_u64;

    let mut code_lengths = vec![0_u8; max_code_index + 1];
    let mut code_index = min_code_index;
    while code_index <= max_code_index {
        let code_len = read_bits(6, &mut code_bits, &mut code_bit_count, packed)?;

        if code_len == LONG_ZEROCODE_RUN {
            let zerun_bits = read_bits(8, &mut code_bits, &mut code_bit_count, packed)?;
            let zerun = usize::try_from(zerun_bits + SHORTEST_LONG_RUN).unwrap();

            if code_index + zerun > max_code_index + 1 {
                return Err(Error::invalid(TABLE_TOO_LONG));
            }

            code_index += zerun;
        } else if code_len >= SHORT_ZEROCODE_RUN {
            let duplication_count = usize::try_from(code_len - SHORT_ZEROCODE_RUN + 2).unwrap();
            if code_index + duplication_count > max_code_index + 1 {
                return Err(Error::invalid(TABLE_TOO_LONG));
            }

            code_index += duplication_count;
        } else {
            code_lengths[code_index] = code_len as u8; // < SHORT_ZEROCODE_RUN
            code_index += 1;
        }
    }

    Ok(code_lengths)
}

// TODO Use BitStreamReader for all the bit reads?!
#[inline]
fn read_bits(
    count: u64,
    code_bits: &mut u64,
    code_bit_count: &mut u64,
    input: &mut impl Read,
) -> Result<u64> {
    while *code_bit_count < count {
        read_byte(code_bits, code_bit_count, input)?;
    }

    *code_bit_count -= count;
    Ok((*code_bits >> *code_bit_count) & ((1 << count) - 1))
}

#[inline]
fn read_byte(code_bits: &mut u64, bit_count: &mut u64, input: &mut impl Read) -> UnitResult {
    *code_bits = (*code_bits << 8) | u64::from(u8::read_ne(input)?);
    *bit_count += 8;
    Ok(())
}

fn count_frequencies(data: &[u16]) -> Vec<u64> {
    let mut frequencies = vec![0_u64; ENCODING_TABLE_SIZE];

    for value in data {
        frequencies[*value as usize] += 1;
    }

    frequencies
}

/// Appends bits to a byte vector, the first bit written the most significant
/// bit of its byte: the bit stream that `BitReader` reads.
///
/// Pending bits wait in a 64-bit register and leave it 32 at a time (the
/// crate's encoder wrote every byte through `io::Write`). Codes of up to 58
/// bits are written in two parts, so none of a code's bits is lost.
struct BitWriter<'a> {
    out: &'a mut Vec<u8>,
    /// The pending bits are the register's lowest `pending`; bits above them
    /// are stale.
    register: u64,
    pending: u32,
}

impl<'a> BitWriter<'a> {
    fn new(out: &'a mut Vec<u8>) -> Self {
        Self {
            out,
            register: 0,
            pending: 0,
        }
    }

    /// Writes the lowest `count` bits of `bits` (`count` ≤ 64; no bit of
    /// `bits` above them may be set).
    #[inline(always)]
    fn write(&mut self, count: u64, bits: u64) {
        if count > 32 {
            self.write_short((count - 32) as u32, bits >> 32);
            self.write_short(32, bits & 0xFFFF_FFFF);
        } else {
            self.write_short(count as u32, bits);
        }
    }

    /// `count` ≤ 32: with at most 31 bits pending, the register holds both.
    #[inline(always)]
    fn write_short(&mut self, count: u32, bits: u64) {
        debug_assert!(count <= 32 && self.pending < 32);
        self.register = (self.register << count) | bits;
        self.pending += count;
        if self.pending >= 32 {
            self.pending -= 32;
            self.out.extend_from_slice(&((self.register >> self.pending) as u32).to_be_bytes());
        }
    }

    #[inline(always)]
    fn write_code(&mut self, scode: u64) {
        self.write(length(scode), code(scode));
    }

    /// Writes the whole bytes still pending, then the last bits (if any) in
    /// the high end of one more byte. Returns how many bits that last byte
    /// holds (0–7).
    fn finish(mut self) -> u64 {
        while self.pending >= 8 {
            self.pending -= 8;
            self.out.push((self.register >> self.pending) as u8);
        }
        if self.pending > 0 {
            self.out.push((self.register << (8 - self.pending)) as u8);
        }
        u64::from(self.pending)
    }
}

#[inline(always)]
fn send_code(scode: u64, run_count: u64, run_code: u64, out: &mut BitWriter<'_>) {
    // Output a run of runCount instances of the symbol sCount.
    // Output the symbols explicitly, or if that is shorter, output
    // the sCode symbol once followed by a runCode symbol and runCount
    // expressed as an 8-bit number.
    if length(scode) + length(run_code) + 8 < length(scode) * run_count {
        out.write_code(scode);
        out.write_code(run_code);
        out.write(8, run_count);
    } else {
        for _ in 0..=run_count {
            out.write_code(scode);
        }
    }
}

/// Appends the data's codes to `out`; returns how many bits they take.
fn encode_with_frequencies(
    frequencies: &[u64],
    uncompressed: &[u16],
    run_length_code: usize,
    out: &mut Vec<u8>,
) -> u64 {
    let start_position = out.len();
    let mut writer = BitWriter::new(out);
    let run_code = frequencies[run_length_code];

    let mut run_start_value = uncompressed[0];
    let mut run_length = 0;

    // Loop on input values
    for &current_value in &uncompressed[1..] {
        // Count same values or send code
        if run_start_value == current_value && run_length < 255 {
            run_length += 1;
        } else {
            send_code(frequencies[run_start_value as usize], run_length, run_code, &mut writer);
            run_length = 0;
        }

        run_start_value = current_value;
    }

    // Send remaining code
    send_code(frequencies[run_start_value as usize], run_length, run_code, &mut writer);

    let last_bits = writer.finish();
    // Every byte but a partial last one counts whole.
    let whole_bytes = (out.len() - start_position) as u64 - u64::from(last_bits > 0);
    whole_bytes * 8 + last_bits
}

/// Pack an encoding table:
/// 	- only code lengths, not actual codes, are stored
/// 	- runs of zeroes are compressed as follows:
/// ```md
/// 	  unpacked		packed
/// 	  --------------------------------
/// 	  1 zero		0	(6 bits)
/// 	  2 zeroes		59
/// 	  3 zeroes		60
/// 	  4 zeroes		61
/// 	  5 zeroes		62
/// 	  n zeroes (6 or more)	63 n-6	(6 + 8 bits)
/// ```
fn pack_encoding_table(frequencies: &[u64], min_index: usize, max_index: usize, out: &mut Vec<u8>) {
    let mut out = BitWriter::new(out);

    let mut frequency_index = min_index;
    while frequency_index <= max_index {
        // TODO slice iteration?
        let code_length = length(frequencies[frequency_index]);

        if code_length == 0 {
            let mut zero_run = 1;

            while frequency_index < max_index && zero_run < LONGEST_LONG_RUN {
                if length(frequencies[frequency_index + 1]) > 0 {
                    break;
                }

                frequency_index += 1;
                zero_run += 1;
            }

            if zero_run >= 2 {
                if zero_run >= SHORTEST_LONG_RUN {
                    out.write(6, LONG_ZEROCODE_RUN);
                    out.write(8, zero_run - SHORTEST_LONG_RUN);
                } else {
                    out.write(6, SHORT_ZEROCODE_RUN + zero_run - 2);
                }

                frequency_index += 1; // we must increment or else this may go very wrong
                continue;
            }
        }

        out.write(6, code_length);
        frequency_index += 1;
    }

    out.finish();
}

/// Build a "canonical" Huffman code table:
///    - for each (uncompressed) symbol, code contains the length of the
///      corresponding code (in the compressed data)
///    - canonical codes are computed and stored in code
///    - the rules for constructing canonical codes are as follows:
///      * shorter codes (if filled with zeroes to the right) have a numerically
///        higher value than longer codes
///      * for codes with the same length, numerical values increase with
///        numerical symbol values
///    - because the canonical code table can be constructed from symbol lengths
///      alone, the code table can be transmitted without sending the actual
///      code values
///    - see <http://www.compressconsult.com/huffman>/
fn build_canonical_table(code_table: &mut [u64]) -> UnitResult {
    debug_assert_eq!(code_table.len(), ENCODING_TABLE_SIZE);

    let mut count_per_code = [0_u64; MAX_CODE_LENGTH + 1];

    for &code in code_table.iter() {
        count_per_code[u64_to_usize(code, "table entry")?] += 1;
    }

    let mut count_per_code = first_code_per_length(&count_per_code);

    // code[i] contains the length, l, of the
    // code for symbol i.  Assign the next available
    // code of length l to the symbol and store both
    // l and the code in code[i]. // TODO iter + filter ?
    for symbol_length in code_table.iter_mut() {
        let current_length = *symbol_length;
        let code_index = u64_to_usize(current_length, "huffman code index")?;
        if current_length > 0 {
            *symbol_length = current_length | (count_per_code[code_index] << 6);
            count_per_code[code_index] += 1;
        }
    }

    Ok(())
}

/// For each length from 58 through 1, the numerically lowest canonical code of
/// that length, given how many symbols have each length (the count of length 0
/// is not used).
fn first_code_per_length(
    count_per_length: &[u64; MAX_CODE_LENGTH + 1],
) -> [u64; MAX_CODE_LENGTH + 1] {
    let mut first_codes = [0_u64; MAX_CODE_LENGTH + 1];
    let mut code = 0_u64;
    for (first_code, &count) in first_codes.iter_mut().zip(count_per_length).rev() {
        *first_code = code;
        code = (code + count) >> 1;
    }
    first_codes
}

/// Compute Huffman codes (based on frq input) and store them in frq:
///    - code structure is : [63:lsb - 6:msb] | [5-0: bit length];
///    - max code length is 58 bits;
///    - codes outside the range [im-iM] have a null length (unused values);
///    - original frequencies are destroyed;
///    - encoding tables are used by `hufEncode()` and `hufBuildDecTable()`;
///
/// NB: The following code "(*a == *b) && (a > b))" was added to ensure
///     elements in the heap with the same value are sorted by index.
///     This is to ensure, the STL `make_heap()/pop_heap()/push_heap()` methods
///     produced a resultant sorted heap that is identical across OSes.
fn build_encoding_table(
    frequencies: &mut [u64], // input frequencies, output encoding table
) -> Result<(usize, usize)> // return frequency max min range
{
    debug_assert_eq!(frequencies.len(), ENCODING_TABLE_SIZE);

    /// Frequency with position, used for `MinHeap`.
    #[derive(Eq, PartialEq, Copy, Clone)]
    struct HeapFrequency {
        position: usize,
        frequency: u64,
    }

    impl Ord for HeapFrequency {
        fn cmp(&self, other: &Self) -> Ordering {
            other.frequency.cmp(&self.frequency).then_with(|| other.position.cmp(&self.position))
        }
    }

    impl PartialOrd for HeapFrequency {
        fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
            Some(self.cmp(other))
        }
    }

    // This function assumes that when it is called, array frq
    // indicates the frequency of all possible symbols in the data
    // that are to be Huffman-encoded.  (frq[i] contains the number
    // of occurrences of symbol i in the data.)
    //
    // The loop below does three things:
    //
    // 1) Finds the minimum and maximum indices that point to non-zero entries in
    //    frq:
    //
    //     frq[im] != 0, and frq[i] == 0 for all i < im
    //     frq[iM] != 0, and frq[i] == 0 for all i > iM
    //
    // 2) Fills array fHeap with pointers to all non-zero entries in frq.
    //
    // 3) Initializes array hlink such that hlink[i] == i for all array entries.

    // We need to use vec here or we overflow the stack.
    let mut links = vec![0_usize; ENCODING_TABLE_SIZE];
    let mut frequency_heap = vec![0_usize; ENCODING_TABLE_SIZE];

    // This is a good solution since we don't have usize::MAX items (no panics or
    // UB), and since this is short-circuit, it stops at the first in order non
    // zero element.
    let min_frequency_index = frequencies.iter().position(|f| *f != 0).unwrap_or(0);

    let mut max_frequency_index = 0;
    let mut frequency_count = 0;

    // assert bounds check to optimize away bounds check in loops
    assert!(links.len() >= ENCODING_TABLE_SIZE);
    assert!(frequencies.len() >= ENCODING_TABLE_SIZE);

    for index in min_frequency_index..ENCODING_TABLE_SIZE {
        links[index] = index; // TODO for x in links.iter().enumerate()

        if frequencies[index] != 0 {
            frequency_heap[frequency_count] = index;
            max_frequency_index = index;
            frequency_count += 1;
        }
    }

    // Add a pseudo-symbol, with a frequency count of 1, to frq;
    // adjust the fHeap and hlink array accordingly.  Function
    // hufEncode() uses the pseudo-symbol for run-length encoding.

    max_frequency_index += 1;
    frequencies[max_frequency_index] = 1;
    frequency_heap[frequency_count] = max_frequency_index;
    frequency_count += 1;

    // Build an array, scode, such that scode[i] contains the number
    // of bits assigned to symbol i.  Conceptually this is done by
    // constructing a tree whose leaves are the symbols with non-zero
    // frequency:
    //
    //     Make a heap that contains all symbols with a non-zero frequency,
    //     with the least frequent symbol on top.
    //
    //     Repeat until only one symbol is left on the heap:
    //
    //         Take the two least frequent symbols off the top of the heap.
    //         Create a new node that has first two nodes as children, and
    //         whose frequency is the sum of the frequencies of the first
    //         two nodes.  Put the new node back into the heap.
    //
    // The last node left on the heap is the root of the tree.  For each
    // leaf node, the distance between the root and the leaf is the length
    // of the code for the corresponding symbol.
    //
    // The loop below doesn't actually build the tree; instead we compute
    // the distances of the leaves from the root on the fly.  When a new
    // node is added to the heap, then that node's descendants are linked
    // into a single linear list that starts at the new node, and the code
    // lengths of the descendants (that is, their distance from the root
    // of the tree) are incremented by one.
    let mut heap = BinaryHeap::with_capacity(frequency_count);
    for index in frequency_heap.drain(..frequency_count) {
        heap.push(HeapFrequency {
            position: index,
            frequency: frequencies[index],
        });
    }

    let mut s_code = vec![0_u64; ENCODING_TABLE_SIZE];

    while frequency_count > 1 {
        // Find the indices, mm and m, of the two smallest non-zero frq
        // values in fHeap, add the smallest frq to the second-smallest
        // frq, and remove the smallest frq value from fHeap.
        let (high_position, low_position) = {
            let smallest_frequency = heap.pop().expect("heap empty bug");
            frequency_count -= 1;

            let mut second_smallest_frequency = heap.peek_mut().expect("heap empty bug");
            second_smallest_frequency.frequency += smallest_frequency.frequency;

            (second_smallest_frequency.position, smallest_frequency.position)
        };

        // The entries in scode are linked into lists with the
        // entries in hlink serving as "next" pointers and with
        // the end of a list marked by hlink[j] == j.
        //
        // Traverse the lists that start at scode[m] and scode[mm].
        // For each element visited, increment the length of the
        // corresponding code by one bit. (If we visit scode[j]
        // during the traversal, then the code for symbol j becomes
        // one bit longer.)
        //
        // Merge the lists that start at scode[m] and scode[mm]
        // into a single list that starts at scode[m].

        // Add a bit to all codes in the first list.
        let mut index = high_position; // TODO fold()
        loop {
            s_code[index] += 1;
            debug_assert!(s_code[index] <= 58);

            // merge the two lists
            if links[index] == index {
                links[index] = low_position;
                break;
            }

            index = links[index];
        }

        // Add a bit to all codes in the second list
        let mut index = low_position; // TODO fold()
        loop {
            s_code[index] += 1;
            debug_assert!(s_code[index] <= 58);

            if links[index] == index {
                break;
            }

            index = links[index];
        }
    }

    // Build a canonical Huffman code table, replacing the code
    // lengths in scode with (code, code length) pairs.  Copy the
    // code table from scode into frq.
    build_canonical_table(&mut s_code)?;
    frequencies.copy_from_slice(&s_code);

    Ok((min_frequency_index, max_frequency_index))
}

#[inline]
const fn length(code: u64) -> u64 {
    code & 63
}
#[inline]
const fn code(code: u64) -> u64 {
    code >> 6
}

const INVALID_BIT_COUNT: &str = "invalid number of bits";
const INVALID_TABLE_ENTRY: &str = "invalid code table entry";
const NOT_ENOUGH_DATA: &str = "decoded data are shorter than expected";
const INVALID_TABLE_SIZE: &str = "unexpected end of code table data";
const TABLE_TOO_LONG: &str = "code table is longer than expected";
const INVALID_CODE: &str = "invalid code";
const TOO_MUCH_DATA: &str = "decoded data are longer than expected";

#[cfg(test)]
mod test {
    use rand::{Rng, SeedableRng};

    use super::*;

    const UNCOMPRESSED_ARRAY: [u16; 100] = [
        3852, 2432, 33635, 49381, 10100, 15095, 62693, 63738, 62359, 5013, 7715, 59875, 28182,
        34449, 19983, 20399, 63407, 29486, 4877, 26738, 44815, 14042, 46091, 48228, 25682, 35412,
        7582, 65069, 6632, 54124, 13798, 27503, 52154, 61961, 30474, 46880, 39097, 15754, 52897,
        42371, 54053, 14178, 48276, 34591, 42602, 32126, 42062, 31474, 16274, 55991, 2882, 17039,
        56389, 20835, 57057, 54081, 3414, 33957, 52584, 10222, 25139, 40002, 44980, 1602, 48021,
        19703, 6562, 61777, 41582, 201, 31253, 51790, 15888, 40921, 3627, 12184, 16036, 26349,
        3159, 29002, 14535, 50632, 18118, 33583, 18878, 59470, 32835, 9347, 16991, 21303, 26263,
        8312, 14017, 41777, 43240, 3500, 60250, 52437, 45715, 61520,
    ];

    const UNCOMPRESSED_ARRAY_SPECIAL: [u16; 100] = [
        0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 28182, 0, 65534, 0, 65534, 0, 65534, 0, 65534, 0, 0, 0,
        0, 0, 0, 0, 0, 54124, 13798, 27503, 52154, 61961, 30474, 46880, 39097, 15754, 52897, 42371,
        54053, 14178, 48276, 34591, 42602, 32126, 42062, 31474, 16274, 55991, 2882, 17039, 56389,
        20835, 57057, 54081, 3414, 33957, 52584, 10222, 25139, 40002, 44980, 1602, 48021, 19703,
        6562, 61777, 41582, 201, 31253, 51790, 15888, 40921, 3627, 12184, 16036, 26349, 3159,
        29002, 14535, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 65534, 65534, 65534, 65534, 65534, 65534,
        65534, 65534, 65534,
    ];

    const COMPRESSED_ARRAY: [u8; 703] = [
        0xc9, 0x0, 0x0, 0x0, 0x2e, 0xfe, 0x0, 0x0, 0x56, 0x2, 0x0, 0x0, 0xa2, 0x2, 0x0, 0x0, 0x0,
        0x0, 0x0, 0x0, 0x1f, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xd6, 0x47,
        0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0x28, 0x1f, 0xff, 0xff, 0xed, 0x87, 0xff, 0xff, 0xf0,
        0x91, 0xff, 0xf8, 0x1f, 0xf4, 0xf1, 0xff, 0x78, 0x1f, 0xfd, 0xa1, 0xff, 0xff, 0xff, 0xff,
        0xff, 0xff, 0xfa, 0xc7, 0xfe, 0x4, 0x7f, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff,
        0xff, 0xed, 0x1f, 0xf3, 0xf1, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xe8, 0x7, 0xfd, 0xf8,
        0x7f, 0xff, 0xff, 0xff, 0xfd, 0x10, 0x7f, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0x51, 0xff,
        0xff, 0xff, 0xff, 0xfe, 0x1, 0xff, 0x73, 0x1f, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff,
        0xff, 0xff, 0xff, 0xff, 0xff, 0xfe, 0x0, 0x7f, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff,
        0xff, 0xff, 0xff, 0xfc, 0xa4, 0x7f, 0xf5, 0x7, 0xfc, 0x48, 0x7f, 0xe0, 0x47, 0xff, 0xff,
        0xf5, 0x91, 0xff, 0xff, 0xff, 0xff, 0xf1, 0xf1, 0xff, 0xff, 0xff, 0xff, 0xf8, 0x21, 0xff,
        0x7f, 0x1f, 0xf8, 0xd1, 0xff, 0xe7, 0x1f, 0xff, 0xff, 0xff, 0xff, 0xbc, 0x1f, 0xf2, 0x91,
        0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0x1c, 0x1f, 0xff, 0xff, 0xff, 0xff, 0xe7,
        0x1f, 0xff, 0xff, 0xff, 0xff, 0xff, 0xfc, 0x8c, 0x7f, 0xff, 0xff, 0xc, 0x1f, 0xff, 0xff,
        0xe5, 0x7, 0xff, 0xff, 0xfa, 0x81, 0xff, 0xff, 0xff, 0x20, 0x7f, 0xff, 0xff, 0xff, 0xff,
        0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff,
        0xff, 0xff, 0xff, 0xff, 0xff, 0xfe, 0xbc, 0x7f, 0xff, 0xff, 0xff, 0xfc, 0x38, 0x7f, 0xff,
        0xff, 0xff, 0xfc, 0xd0, 0x7f, 0xd3, 0xc7, 0xff, 0xff, 0xf7, 0x91, 0xff, 0xff, 0xff, 0xff,
        0xfe, 0xc1, 0xff, 0xff, 0xff, 0xff, 0xf9, 0x61, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xc7,
        0x87, 0xff, 0xff, 0xfd, 0x81, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xf1, 0x87, 0xff, 0xff,
        0xff, 0xff, 0xfe, 0x87, 0xff, 0x58, 0x7f, 0xff, 0xff, 0xff, 0xfd, 0xec, 0x7f, 0xff, 0xff,
        0xff, 0xfe, 0xd0, 0x7f, 0xff, 0xff, 0xff, 0xff, 0x6c, 0x7f, 0xcb, 0x47, 0xff, 0xff, 0xf3,
        0x61, 0xff, 0xff, 0xff, 0x80, 0x7f, 0xe1, 0xc7, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0x1f,
        0x1f, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff,
        0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0x18, 0x1f, 0xff, 0xff,
        0xff, 0xff, 0xff, 0xfd, 0xcc, 0x7f, 0xff, 0xff, 0xff, 0xff, 0xff, 0xf8, 0x11, 0xff, 0xff,
        0xff, 0xff, 0xf8, 0x41, 0xff, 0xbc, 0x1f, 0xff, 0xff, 0xc4, 0x47, 0xff, 0xff, 0xf2, 0x91,
        0xff, 0xe0, 0x1f, 0xff, 0xff, 0xff, 0xff, 0x6d, 0x1f, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff,
        0xff, 0xff, 0xff, 0xff, 0xff, 0x2, 0x1f, 0xf9, 0xe1, 0xff, 0xff, 0xff, 0xff, 0xfc, 0xe1,
        0xff, 0xff, 0xfd, 0xb0, 0x7f, 0xff, 0xff, 0xff, 0xff, 0xff, 0xe1, 0xff, 0xff, 0xff, 0xff,
        0xff, 0xff, 0xff, 0xff, 0x5a, 0x1f, 0xfc, 0x81, 0xbf, 0x29, 0x1b, 0xff, 0xff, 0xff, 0xff,
        0xff, 0xff, 0xff, 0xf3, 0x61, 0xbf, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xc8, 0x1b,
        0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xf6, 0xb1, 0xbf, 0xff, 0xfd, 0x80, 0x6f, 0xff,
        0xff, 0xf, 0x1b, 0xf8, 0xc1, 0xbf, 0xff, 0xfc, 0xb4, 0x6f, 0xff, 0xff, 0xff, 0xff, 0xff,
        0xff, 0xff, 0xda, 0x46, 0xfc, 0x54, 0x6f, 0xc9, 0x6, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff,
        0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0x21, 0x1b, 0xff, 0xff, 0xe0, 0x86, 0xff, 0xff,
        0xff, 0xff, 0xe2, 0xc6, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff,
        0xff, 0xff, 0xff, 0xff, 0xff, 0xf3, 0x91, 0xbf, 0xff, 0xfe, 0x24, 0x6f, 0xff, 0xff, 0x6b,
        0x1b, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xfd, 0xb1, 0xbf, 0xfa, 0x1b, 0xfb, 0x11,
        0xbf, 0xff, 0xfe, 0x8, 0x6f, 0xff, 0xff, 0x42, 0x1b, 0xff, 0xff, 0xff, 0xff, 0xb9, 0x1b,
        0xff, 0xff, 0xcf, 0xc6, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xf1, 0x31,
        0x86, 0x10, 0x9, 0xb4, 0xe4, 0x4c, 0xf7, 0xef, 0x42, 0x87, 0x6a, 0xb5, 0xc2, 0x34, 0x9e,
        0x2f, 0x12, 0xae, 0x21, 0x68, 0xf2, 0xa8, 0x74, 0x37, 0xe1, 0x98, 0x14, 0x59, 0x57, 0x2c,
        0x24, 0x3b, 0x35, 0x6c, 0x1b, 0x8b, 0xcc, 0xe6, 0x13, 0x38, 0xc, 0x8e, 0xe2, 0xc, 0xfe,
        0x49, 0x73, 0xbc, 0x2b, 0x7b, 0x9, 0x27, 0x79, 0x14, 0xc, 0x94, 0x42, 0xf8, 0x7c, 0x1,
        0x8d, 0x26, 0xde, 0x87, 0x26, 0x71, 0x50, 0x45, 0xc6, 0x28, 0x40, 0xd5, 0xe, 0x8d, 0x8,
        0x1e, 0x4c, 0xa4, 0x79, 0x57, 0xf0, 0xc3, 0x6d, 0x5c, 0x6d, 0xc0,
    ];

    fn fill(rng: &mut impl Rng, size: usize) -> Vec<u16> {
        if rng.gen_bool(0.2) {
            let value = if rng.gen_bool(0.5) {
                0
            } else {
                u16::MAX
            };
            return vec![value; size];
        }

        let mut data = vec![0_u16; size];

        data.iter_mut().for_each(|v| {
            *v = rng.gen_range(0_u16..u16::MAX);
        });

        data
    }

    /// Inputs of the test against the published crate's encoder: uniform
    /// values; a few skewed values with runs of every length up to 300;
    /// Fibonacci counts (codes of up to 27 bits), shuffled; short streams.
    fn encoder_test_inputs() -> Vec<Vec<u16>> {
        use rand::seq::SliceRandom;

        let mut random = rand::rngs::StdRng::seed_from_u64(7);
        let mut inputs: Vec<Vec<u16>> = vec![(0..65_536).map(|_| random.gen::<u16>()).collect()];

        let mut skewed = Vec::new();
        while skewed.len() < 200_000 {
            let value = (random.gen::<f64>().powi(6) * 2000.0) as u16;
            let run = if random.gen_bool(0.1) {
                random.gen_range(1..300)
            } else {
                1
            };
            skewed.extend(std::iter::repeat(value).take(run));
        }
        inputs.push(skewed);

        let mut fibonacci = Vec::new();
        let (mut count, mut next) = (1_usize, 1_usize);
        for symbol in 0..28_u16 {
            fibonacci.extend(std::iter::repeat(symbol * 997 + 3).take(count));
            (count, next) = (next, count + next);
        }
        fibonacci.shuffle(&mut random);
        inputs.push(fibonacci);

        for length in 1..40 {
            inputs.push((0..length).map(|_| random.gen_range(0..5_u16)).collect());
        }
        inputs
    }

    /// FNV-1a over every encoded stream and its length.
    fn checksum_of_encodings(inputs: &[Vec<u16>]) -> u64 {
        let mut hash = 0xcbf2_9ce4_8422_2325_u64;
        for input in inputs {
            let encoded = compress(input).unwrap();
            for &byte in (encoded.len() as u64).to_le_bytes().iter().chain(&encoded) {
                hash = (hash ^ u64::from(byte)).wrapping_mul(0x100_0000_01b3);
            }
        }
        hash
    }

    /// This encoder writes the bytes that the published crate's encoder
    /// (exr 1.74.2, which wrote every byte through `io::Write`) wrote for the
    /// same inputs: the checksum is the published encoder's, run on
    /// `encoder_test_inputs` in a copy of that crate.
    #[test]
    fn encodes_as_the_published_crate_did() {
        assert_eq!(checksum_of_encodings(&encoder_test_inputs()), 0xcc04_0ac4_dea1_b2c1);
    }

    /// Test using both input and output from a custom ILM OpenEXR test.
    #[test]
    fn compression_comparation() {
        let raw = compress(&UNCOMPRESSED_ARRAY).unwrap();
        assert_eq!(raw, COMPRESSED_ARRAY.to_vec());
    }

    #[test]
    fn round_trip() {
        let mut random = rand::rngs::StdRng::from_seed(SEED);
        let raw = fill(&mut random, u16::MAX as usize);

        let compressed = compress(&raw).unwrap();
        let uncompressed = decompress(&compressed, raw.len()).unwrap();

        assert_eq!(uncompressed, raw);
    }

    #[test]
    fn repetitions_special() {
        let raw = UNCOMPRESSED_ARRAY_SPECIAL;

        let compressed = compress(&raw).unwrap();
        let uncompressed = decompress(&compressed, raw.len()).unwrap();

        assert_eq!(uncompressed, raw.to_vec());
    }

    #[test]
    fn round_trip100() {
        let mut random = rand::rngs::StdRng::from_seed(SEED);

        for size_multiplier in 1..10 {
            let raw = fill(&mut random, size_multiplier * 50_000);

            let compressed = compress(&raw).unwrap();
            let uncompressed = decompress(&compressed, raw.len()).unwrap();

            assert_eq!(uncompressed, raw);
        }
    }

    #[test]
    fn test_zeroes() {
        let uncompressed: &[u16] =
            &[0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0];

        let compressed = compress(uncompressed).unwrap();
        let decompressed = decompress(&compressed, uncompressed.len()).unwrap();

        assert_eq!(uncompressed, decompressed.as_slice());
    }

    /// The longest code length in a compressed stream's table.
    fn longest_code(compressed: &[u8]) -> u64 {
        let mut rest = &compressed[20..];
        let min = u32::from_le_bytes(compressed[0..4].try_into().unwrap()) as usize;
        let max = u32::from_le_bytes(compressed[4..8].try_into().unwrap()) as usize;
        let lengths = read_code_lengths(&mut rest, min, max).unwrap();
        u64::from(*lengths.iter().max().unwrap())
    }

    /// The bit writer against one bit at a time: codes of 0–58 bits in any
    /// order, the last byte padded with zeros.
    #[test]
    fn bit_writer_writes_every_bit_in_order() {
        let mut random = rand::rngs::StdRng::from_seed(SEED);
        for _ in 0..500 {
            let mut bytes = Vec::new();
            let mut expected = Vec::new();
            let mut writer = BitWriter::new(&mut bytes);
            for _ in 0..random.gen_range(0..80) {
                let count = random.gen_range(0..=58_u64);
                let bits = if count == 0 {
                    0
                } else {
                    random.gen::<u64>() >> (64 - count)
                };
                writer.write(count, bits);
                expected.extend((0..count).rev().map(|bit| (bits >> bit) & 1 == 1));
            }
            let last_bits = writer.finish();

            assert_eq!(last_bits, expected.len() as u64 % 8);
            assert_eq!(bytes.len(), (expected.len() + 7) / 8);
            for (index, byte) in bytes.iter().enumerate() {
                for bit in 0..8 {
                    let written = byte >> (7 - bit) & 1 == 1;
                    let wanted = expected.get(index * 8 + bit).copied().unwrap_or(false);
                    assert_eq!(written, wanted, "byte {} bit {}", index, bit);
                }
            }
        }
    }

    /// Codes far longer than the primary table's `PRIMARY_BITS`, up to the
    /// 57 bits that a 64-bit refill cannot always hold: 57 symbols with
    /// Fibonacci frequencies (and the run code, frequency 1) make a chain.
    #[test]
    fn codes_up_to_57_bits_round_trip() {
        let mut frequencies = vec![0_u64; ENCODING_TABLE_SIZE];
        let (mut a, mut b) = (1_u64, 1_u64);
        for symbol in 0..57 {
            frequencies[1000 + symbol] = a;
            (a, b) = (b, a + b);
        }

        let mut random = rand::rngs::StdRng::from_seed(SEED);
        for length in [1, 2, 3, 7, 100, 5000] {
            let raw: Vec<u16> = (0..length)
                .map(|index| match random.gen_range(0..4) {
                    0 => 1000 + (index % 57) as u16, // every symbol, the rarest too
                    1 => 1056,                       // long runs of the longest code
                    2 => 1000 + random.gen_range(0..57),
                    _ => 1056 - random.gen_range(0..3),
                })
                .collect();

            let compressed = compress_with_frequencies(&raw, frequencies.clone()).unwrap();
            assert!(longest_code(&compressed) >= 56, "{}", longest_code(&compressed));
            assert_eq!(decompress(&compressed, raw.len()).unwrap(), raw, "length {}", length);
        }
    }

    /// Geometric frequencies over thousands of symbols: codes of every length
    /// from 1 to beyond the primary table, short runs and long.
    #[test]
    fn codes_of_every_length_round_trip() {
        let mut random = rand::rngs::StdRng::from_seed(SEED);
        for spread in [2.0_f64, 30.0, 400.0, 6000.0] {
            let mut raw = Vec::new();
            while raw.len() < 200_000 {
                let value = (-spread * random.gen::<f64>().ln()).min(f64::from(u16::MAX)) as u16;
                let run = if random.gen_bool(0.02) {
                    random.gen_range(1..600)
                } else {
                    1
                };
                raw.extend(std::iter::repeat(value).take(run));
            }

            let compressed = compress(&raw).unwrap();
            if spread >= 400.0 {
                assert!(longest_code(&compressed) > u64::from(PRIMARY_BITS));
            }
            assert_eq!(decompress(&compressed, raw.len()).unwrap(), raw, "spread {}", spread);
        }
    }

    /// Few symbols (all codes short, the run code too, zeros a code) in
    /// streams of every length: no code is taken from the last byte's
    /// padding, and a run's count is never taken for a code.
    #[test]
    fn short_streams_of_few_symbols_round_trip() {
        let mut random = rand::rngs::StdRng::from_seed(SEED);
        for symbols in 1..5_u16 {
            for length in 1..80 {
                let raw: Vec<u16> = (0..length)
                    .map(|_| {
                        if random.gen_bool(0.8) {
                            random.gen_range(0..symbols)
                        } else {
                            7
                        }
                    })
                    .collect();
                let compressed = compress(&raw).unwrap();
                assert_eq!(decompress(&compressed, raw.len()).unwrap(), raw, "{:?}", raw);
            }
        }
    }

    /// Altered and truncated streams give an error or some data, never a panic,
    /// and a stream read with the wrong length is an error.
    #[test]
    fn altered_streams_are_errors_not_panics() {
        let mut random = rand::rngs::StdRng::from_seed(SEED);
        let raw: Vec<u16> =
            (0..20_000).map(|_| (-300.0 * random.gen::<f64>().ln()) as u16).collect();
        let compressed = compress(&raw).unwrap();

        assert!(decompress(&compressed, raw.len() - 1).is_err());
        assert!(decompress(&compressed, raw.len() + 1).is_err());

        for _ in 0..3000 {
            let mut altered = compressed.clone();
            match random.gen_range(0..3) {
                0 => altered.truncate(random.gen_range(0..compressed.len())),
                1 => {
                    let index = random.gen_range(0..altered.len());
                    altered[index] ^= 1 << random.gen_range(0..8);
                }
                _ => {
                    for _ in 0..8 {
                        let index = random.gen_range(0..altered.len());
                        altered[index] = random.gen();
                    }
                }
            }
            let _ = decompress(&altered, raw.len());
        }
    }

    /// Every one of the stream's five header numbers set to values around
    /// and far from its own (the smallest symbol above the largest among
    /// them): an error or a decoding, never a panic.
    #[test]
    fn altered_headers_are_errors_not_panics() {
        let mut random = rand::rngs::StdRng::from_seed(SEED);
        let raw: Vec<u16> =
            (0..5_000).map(|_| 1000 + (-30.0 * random.gen::<f64>().ln()) as u16).collect();
        let compressed = compress(&raw).unwrap();
        let header =
            |i: usize| u32::from_le_bytes(compressed[4 * i..4 * i + 4].try_into().unwrap());
        let (min, max) = (header(0), header(1));
        assert!(min < max, "{min} {max}");
        for field in 0..5 {
            let own = header(field);
            let mut values = vec![0, 1, min, max, max + 1, 65_536, 65_537, u32::MAX];
            let near = [own.wrapping_sub(1), own.wrapping_add(1), own / 2, own.wrapping_mul(2)];
            values.extend(near);
            values.extend((0..20).map(|_| random.gen_range(0..70_000)));
            for value in values {
                let mut altered = compressed.clone();
                altered[4 * field..4 * field + 4].copy_from_slice(&value.to_le_bytes());
                let _ = decompress(&altered, raw.len());
            }
        }
        let mut swapped = compressed.clone();
        swapped[0..4].copy_from_slice(&max.to_le_bytes());
        swapped[4..8].copy_from_slice(&min.to_le_bytes());
        assert!(decompress(&swapped, raw.len()).is_err());
    }

    const SEED: [u8; 32] = [
        12, 155, 32, 34, 112, 109, 98, 54, 12, 255, 32, 34, 112, 109, 98, 55, 12, 155, 32, 34, 12,
        109, 98, 54, 12, 35, 32, 34, 112, 109, 48, 54,
    ];
}
