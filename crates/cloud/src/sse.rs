//! Server-Sent Events read as the HTML standard's event-stream interpretation says (WHATWG
//! HTML §9.2.6), sans-IO: bytes in, whole events out, whatever the chunks — a character split
//! across two reads, `\r\n`, `\r` or `\n` line ends, comments, several `data:` lines, a
//! leading byte-order mark. `canlift watch` and the tests read the portal's streams with it.

/// One event: its type (`message` when the stream names none) and its data (the `data:` lines
/// joined with `\n`). As a schema, the events of the portal's streams: each named, with one
/// line of JSON.
#[derive(Debug, Clone, PartialEq, Eq, utoipa::ToSchema)]
pub struct SseEvent {
    /// The event type: `value`, `online`, `event` or `alarm` on the portal's streams.
    #[schema(pattern = "^(value|online|event|alarm)$")]
    pub event: String,
    /// The data: a ValueMessage, OnlineMessage, BusEventMessage or an alarm, as JSON.
    pub data: String,
}

/// The parser's state between chunks.
#[derive(Debug, Default)]
pub struct SseParser {
    /// Bytes of a line not yet ended.
    line: Vec<u8>,
    /// The last chunk ended in `\r`: a `\n` first in the next one belongs to that line end.
    after_cr: bool,
    /// The first line's byte-order mark is dropped once.
    started: bool,
    /// The event being built.
    event: String,
    data: String,
    has_data: bool,
}

impl SseParser {
    /// The events that `chunk` completes.
    pub fn feed(&mut self, chunk: &[u8]) -> Vec<SseEvent> {
        let mut events = Vec::new();
        for &byte in chunk {
            if std::mem::take(&mut self.after_cr) && byte == b'\n' {
                continue;
            }
            match byte {
                b'\r' | b'\n' => {
                    self.after_cr = byte == b'\r';
                    let line = std::mem::take(&mut self.line);
                    if let Some(event) = self.line_ended(&line) {
                        events.push(event);
                    }
                }
                _ => self.line.push(byte),
            }
        }
        events
    }

    /// A whole line (no line end): an event when it is the empty line that ends one with data.
    fn line_ended(&mut self, line: &[u8]) -> Option<SseEvent> {
        // Lines end only at CR or LF bytes, which no multi-byte UTF-8 sequence contains: a
        // character split across chunks is whole here.
        let mut text = String::from_utf8_lossy(line).into_owned();
        if !std::mem::replace(&mut self.started, true) {
            if let Some(rest) = text.strip_prefix('\u{feff}') {
                text = rest.to_owned();
            }
        }
        if text.is_empty() {
            let event = std::mem::take(&mut self.event);
            let data = std::mem::take(&mut self.data);
            if !std::mem::take(&mut self.has_data) {
                return None;
            }
            return Some(SseEvent {
                event: if event.is_empty() {
                    "message".into()
                } else {
                    event
                },
                data,
            });
        }
        if text.starts_with(':') {
            return None;
        }
        let (field, value) = match text.split_once(':') {
            Some((field, value)) => (field, value.strip_prefix(' ').unwrap_or(value)),
            None => (text.as_str(), ""),
        };
        match field {
            "event" => self.event = value.to_owned(),
            "data" => {
                if self.has_data {
                    self.data.push('\n');
                }
                self.data.push_str(value);
                self.has_data = true;
            }
            // `id` and `retry` matter to a browser reconnecting; the portal's streams send
            // neither, and an unknown field is ignored as the standard says.
            _ => {}
        }
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn all(chunks: &[&[u8]]) -> Vec<SseEvent> {
        let mut p = SseParser::default();
        chunks.iter().flat_map(|c| p.feed(c)).collect()
    }

    fn ev(event: &str, data: &str) -> SseEvent {
        SseEvent {
            event: event.into(),
            data: data.into(),
        }
    }

    #[test]
    fn lines_end_three_ways_and_characters_split_across_chunks() {
        let umlaut = "event: value\r\ndata: {\"value\":\"Tür\"}\r\n\r\n".as_bytes();
        let split = umlaut.iter().position(|&b| b == 0xc3).unwrap() + 1;
        assert_eq!(
            all(&[&umlaut[..split], &umlaut[split..]]),
            vec![ev("value", "{\"value\":\"Tür\"}")]
        );
        // A CR at a chunk's end, its LF in the next: one line end, not two.
        assert_eq!(
            all(&[b"data: a\r", b"\ndata: b\r", b"\n\r", b"\n"]),
            vec![ev("message", "a\nb")]
        );
        assert_eq!(
            all(&[b"data: x\r\rdata: y\n\n"]),
            vec![ev("message", "x"), ev("message", "y")]
        );
        assert_eq!(
            all(&["\u{feff}: comment\nevent:online\ndata:{}\n\n".as_bytes()]),
            vec![ev("online", "{}")]
        );
        // No data, no event; an empty data line is data.
        assert_eq!(all(&[b"event: x\n\ndata\n\n"]), vec![ev("message", "")]);
    }

    proptest! {
        #[test]
        fn any_chunking_gives_the_same_events(cuts in proptest::collection::vec(0usize..80, 0..8)) {
            let stream = "event: value\r\ndata: {\"v\":\"Türkräfte €\"}\r\n\r\n: ping\n\nevent: online\rdata: {\"online\":true}\r\r".as_bytes();
            let whole = all(&[stream]);
            let mut cuts: Vec<usize> = cuts.into_iter().map(|c| c.min(stream.len())).collect();
            cuts.sort_unstable();
            let mut chunks = Vec::new();
            let mut at = 0;
            for c in cuts {
                chunks.push(&stream[at..c.max(at)]);
                at = c.max(at);
            }
            chunks.push(&stream[at..]);
            prop_assert_eq!(all(&chunks), whole.clone());
            prop_assert_eq!(whole.len(), 2);
        }
    }
}
