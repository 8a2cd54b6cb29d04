//! Framing: `COBS(seq ‖ postcard(message) ‖ CRC-32C-LE) ‖ 0x00`, and a stream
//! decoder that takes bytes in arbitrary chunks.
//!
//! Guarantees (tested, and fuzzed by `fuzz/fuzz_targets/decoder.rs`):
//! - no function here panics on any input;
//! - a frame is yielded only if its COBS body decodes, its CRC matches and the
//!   postcard payload decodes to a message using *every* byte;
//! - after garbage, an over-long run or a corrupted frame, the decoder is back in
//!   sync at the next `0x00`.

use core::marker::PhantomData;

use postcard::experimental::max_size::MaxSize;
use serde::{Serialize, de::DeserializeOwned};

use crate::msg::{Request, ToHost};

/// The CRC: CRC-32C (Castagnoli, `crc::CRC_32_ISCSI`): reflected, polynomial
/// 0x1EDC6F41, init and xor-out 0xFFFFFFFF. Chosen over CRC-16 because the
/// decoder must not accept a corrupted frame even over millions of bytes of
/// line noise; over CRC-32/ISO-HDLC for its better Hamming distance at our
/// frame lengths.
pub const CRC: crc::Crc<u32> = crc::Crc::<u32>::new(&crc::CRC_32_ISCSI);

/// Bytes of the sequence-number header.
pub const SEQ_LEN: usize = 1;
/// Bytes of the CRC trailer.
pub const CRC_LEN: usize = 4;

/// Longest encoded frame (delimiter included) for a payload of at most
/// `max_message` postcard bytes.
pub const fn max_frame_len(max_message: usize) -> usize {
    cobs::max_encoding_length(SEQ_LEN + max_message + CRC_LEN) + 1
}

const fn max(a: usize, b: usize) -> usize {
    if a > b { a } else { b }
}

/// A message type that travels in frames: one per direction.
pub trait Message: Serialize + DeserializeOwned + MaxSize {
    /// Longest frame of this message type on the wire, delimiter included.
    const MAX_FRAME_LEN: usize = max_frame_len(Self::POSTCARD_MAX_SIZE);
}

impl Message for Request {}
impl Message for ToHost {}

/// Longest frame in either direction: the size of every frame buffer.
pub const MAX_FRAME_LEN: usize = max(Request::MAX_FRAME_LEN, ToHost::MAX_FRAME_LEN);

/// Longest unencoded frame body (seq + payload + CRC) in either direction.
const MAX_RAW_LEN: usize =
    SEQ_LEN + max(Request::POSTCARD_MAX_SIZE, ToHost::POSTCARD_MAX_SIZE) + CRC_LEN;

/// A decoded frame.
#[derive(Debug, Clone, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Frame<M> {
    /// Sequence number: the request's for requests and replies, the event
    /// counter for events.
    pub seq: u8,
    /// The message.
    pub msg: M,
}

/// Why a frame could not be encoded or was rejected.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum FrameError {
    /// Encoding: the output buffer is too small (use [`MAX_FRAME_LEN`]).
    BufferTooSmall,
    /// More bytes than [`MAX_FRAME_LEN`] arrived without a delimiter; they were
    /// dropped up to the next delimiter.
    TooLong,
    /// The COBS encoding is invalid.
    Cobs,
    /// Shorter than a sequence number, one payload byte and a CRC.
    TooShort,
    /// CRC mismatch.
    Crc,
    /// CRC matched but the payload is not a valid message (unknown variant,
    /// bad varint, trailing bytes…): likely a peer of another protocol version.
    Payload,
}

impl core::fmt::Display for FrameError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            FrameError::BufferTooSmall => "output buffer too small for the frame",
            FrameError::TooLong => "frame longer than the protocol maximum",
            FrameError::Cobs => "invalid COBS encoding",
            FrameError::TooShort => "frame too short",
            FrameError::Crc => "CRC mismatch",
            FrameError::Payload => "payload does not decode to a message",
        })
    }
}

impl core::error::Error for FrameError {}

/// Encode `msg` with sequence number `seq` into `out`; returns the frame length
/// (delimiter included). `out` of [`MAX_FRAME_LEN`] bytes always suffices.
pub fn encode_frame<M: Message>(seq: u8, msg: &M, out: &mut [u8]) -> Result<usize, FrameError> {
    let mut raw = [0u8; MAX_RAW_LEN];
    raw[0] = seq;
    let payload_len = postcard::to_slice(msg, &mut raw[SEQ_LEN..MAX_RAW_LEN - CRC_LEN])
        .map_err(|_| FrameError::BufferTooSmall)?
        .len();
    let body_len = SEQ_LEN + payload_len;
    let crc = CRC.checksum(&raw[..body_len]);
    raw[body_len..body_len + CRC_LEN].copy_from_slice(&crc.to_le_bytes());
    let raw = &raw[..body_len + CRC_LEN];
    let n = cobs::try_encode(raw, out).map_err(|_| FrameError::BufferTooSmall)?;
    *out.get_mut(n).ok_or(FrameError::BufferTooSmall)? = 0;
    Ok(n + 1)
}

/// Longest [`encode_flushed_frame`] output: a frame and the delimiter before it.
pub const MAX_FLUSHED_FRAME_LEN: usize = MAX_FRAME_LEN + 1;

/// Encode like [`encode_frame`], after a `0x00` (docs/protocol.md §2): should
/// line noise have hidden the delimiter of the frame before, the receiver ends
/// that frame here and this one arrives whole, instead of both being lost.
/// Both ends send every frame this way. `out` of [`MAX_FLUSHED_FRAME_LEN`]
/// bytes always suffices.
pub fn encode_flushed_frame<M: Message>(
    seq: u8,
    msg: &M,
    out: &mut [u8],
) -> Result<usize, FrameError> {
    let (first, rest) = out.split_first_mut().ok_or(FrameError::BufferTooSmall)?;
    *first = 0;
    Ok(1 + encode_frame(seq, msg, rest)?)
}

/// Decode one frame body **in place**: `buf` holds the COBS bytes between two
/// delimiters (without them).
pub fn decode_frame<M: Message>(buf: &mut [u8]) -> Result<Frame<M>, FrameError> {
    let n = cobs::decode_in_place(buf).map_err(|_| FrameError::Cobs)?;
    let raw = buf.get(..n).ok_or(FrameError::Cobs)?;
    if n < SEQ_LEN + 1 + CRC_LEN {
        return Err(FrameError::TooShort);
    }
    let (body, crc) = raw.split_at(n - CRC_LEN);
    let expected = u32::from_le_bytes([crc[0], crc[1], crc[2], crc[3]]);
    if CRC.checksum(body) != expected {
        return Err(FrameError::Crc);
    }
    let (msg, rest) =
        postcard::take_from_bytes::<M>(&body[SEQ_LEN..]).map_err(|_| FrameError::Payload)?;
    if !rest.is_empty() {
        return Err(FrameError::Payload);
    }
    Ok(Frame { seq: body[0], msg })
}

/// Reassembles frames from a byte stream delivered in arbitrary chunks.
///
/// `N` is the buffer size; it defaults to the protocol maximum, which is also
/// the longest frame accepted.
#[derive(Debug)]
pub struct FrameDecoder<M, const N: usize = MAX_FRAME_LEN> {
    buf: [u8; N],
    len: usize,
    /// Bytes were dropped since the last delimiter (frame too long).
    overflowed: bool,
    _msg: PhantomData<fn() -> M>,
}

impl<M: Message, const N: usize> Default for FrameDecoder<M, N> {
    fn default() -> Self {
        Self::new()
    }
}

impl<M: Message, const N: usize> FrameDecoder<M, N> {
    /// An empty decoder.
    pub const fn new() -> Self {
        FrameDecoder { buf: [0; N], len: 0, overflowed: false, _msg: PhantomData }
    }

    /// Forget a partly received frame (e.g. after a reconnect).
    pub fn reset(&mut self) {
        self.len = 0;
        self.overflowed = false;
    }

    /// Bytes of the frame being received.
    pub fn pending(&self) -> usize {
        self.len
    }

    /// Feed one byte; returns a frame or an error when a delimiter completes one.
    pub fn push(&mut self, byte: u8) -> Option<Result<Frame<M>, FrameError>> {
        if byte == 0 {
            return self.finish();
        }
        if self.len < N {
            self.buf[self.len] = byte;
            self.len += 1;
        } else {
            self.overflowed = true;
        }
        None
    }

    /// Feed a chunk; the iterator yields every frame or error it completes.
    /// Bytes after the last delimiter stay buffered for the next chunk. Dropping
    /// the iterator early keeps the unread rest of `chunk` unconsumed.
    pub fn feed<'d, 'c>(&'d mut self, chunk: &'c [u8]) -> Feed<'d, 'c, M, N> {
        Feed { decoder: self, rest: chunk }
    }

    fn finish(&mut self) -> Option<Result<Frame<M>, FrameError>> {
        let (len, overflowed) = (self.len, self.overflowed);
        self.reset();
        if overflowed {
            return Some(Err(FrameError::TooLong));
        }
        if len == 0 {
            // Back-to-back delimiters are allowed (a sender may start every
            // frame with one to flush line noise).
            return None;
        }
        Some(decode_frame(&mut self.buf[..len]))
    }

    /// Append `bytes` (no delimiter among them) to the frame being received.
    fn extend(&mut self, bytes: &[u8]) {
        let room = N - self.len;
        if bytes.len() > room {
            self.buf[self.len..].copy_from_slice(&bytes[..room]);
            self.len = N;
            self.overflowed = true;
        } else {
            self.buf[self.len..self.len + bytes.len()].copy_from_slice(bytes);
            self.len += bytes.len();
        }
    }
}

/// Iterator returned by [`FrameDecoder::feed`].
#[derive(Debug)]
pub struct Feed<'d, 'c, M, const N: usize> {
    decoder: &'d mut FrameDecoder<M, N>,
    rest: &'c [u8],
}

impl<'c, M, const N: usize> Feed<'_, 'c, M, N> {
    /// The part of the chunk not consumed yet.
    pub fn remaining(&self) -> &'c [u8] {
        self.rest
    }
}

impl<M: Message, const N: usize> Iterator for Feed<'_, '_, M, N> {
    type Item = Result<Frame<M>, FrameError>;

    fn next(&mut self) -> Option<Self::Item> {
        while !self.rest.is_empty() {
            match self.rest.iter().position(|&b| b == 0) {
                Some(end) => {
                    self.decoder.extend(&self.rest[..end]);
                    self.rest = &self.rest[end + 1..];
                    if let Some(result) = self.decoder.finish() {
                        return Some(result);
                    }
                }
                None => {
                    self.decoder.extend(self.rest);
                    self.rest = &[];
                }
            }
        }
        None
    }
}
