//! Decoding a captured telegram file (for `amr tools sopas-decode FILE`): CoLa-A or CoLa-B,
//! framed or not (the pysicktim capture has STX/ETX stripped and a trailing LF, notes §4).

use super::command::Reply;
use super::error::{DecodeError, SopasError};
use super::framing::{DEFAULT_MAX_FRAME_LEN, Dialect, ETX, Framer, STX};

/// Decodes the first telegram in `bytes`, whichever dialect and framing it has.
pub fn decode_capture(bytes: &[u8]) -> Result<Reply, SopasError> {
    if bytes.first() == Some(&STX) {
        let mut framer = Framer::new(bytes.len().max(DEFAULT_MAX_FRAME_LEN));
        framer.push(bytes);
        let frame = match framer.next_frame() {
            Some(Ok(frame)) => frame,
            Some(Err(e)) => return Err(e.into()),
            None => return Err(DecodeError::UnexpectedEnd { what: "frame" }.into()),
        };
        return Ok(Reply::decode(frame.dialect, &frame.payload)?);
    }
    // Unframed: ASCII text (maybe with a line end) is CoLa-A, anything with binary bytes CoLa-B.
    let text_end = bytes.iter().rposition(|b| !matches!(b, b'\r' | b'\n' | b' ')).map_or(0, |i| i + 1);
    let text = &bytes[..text_end];
    let ascii = text.iter().all(|&b| (0x20..0x7F).contains(&b) && b != ETX);
    if ascii { Ok(Reply::decode(Dialect::ColaA, text)?) } else { Ok(Reply::decode(Dialect::ColaB, bytes)?) }
}
