//! The socketcand codec, as the client and the hub read it: bytes in arbitrary chunks. No
//! panic; what stays buffered is below one message's bound; frames re-encode to themselves.
#![no_main]

use canbus::socketcand::codec::{encode_control, parse, Decoder, Message, MAX_MESSAGE_LEN};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Some((&chunk, bytes)) = data.split_first() else {
        return;
    };
    let chunk = usize::from(chunk).max(1);
    let mut decoder = Decoder::new();
    for piece in bytes.chunks(chunk) {
        decoder.feed(piece);
        while let Some(result) = decoder.next_message() {
            let Ok(message) = result else { continue };
            let text = encode_control(&message);
            let again = parse(text.as_bytes())
                .unwrap_or_else(|e| panic!("{message:?} encodes to {text:?}, which fails: {e}"));
            if matches!(message, Message::Send(_) | Message::Frame(_)) {
                assert_eq!(again, message, "{text}");
            }
        }
        assert!(
            decoder.pending() < MAX_MESSAGE_LEN,
            "{} bytes held after draining",
            decoder.pending()
        );
    }
});
