//! What the broker sends an MQTT 3.1.1 client, with each PUBLISH larger
//! than `[mqtt] max_message_bytes` cut down to its topic: pure, on bytes
//! as they come, whatever their chunks.
//!
//! rumqttc's 3.1.1 client drops the connection on a packet above its size
//! limit (and MQTT 3.1.1, unlike MQTT 5, cannot tell the broker a limit):
//! a large retained message would then cost the connection at every
//! reconnect, for as long as it is retained. So the Sparkplug connection's
//! bytes pass through this filter first (`super::relay`): a PUBLISH over the
//! limit goes on as the same PUBLISH (flags, topic, packet id) with an
//! empty payload, so the client acknowledges it as usual and the broker's
//! QoS flow completes, while the payload's bytes are skipped as they
//! arrive, never held. What was cut is reported ([`Cut`]).

/// A PUBLISH cut down to its topic.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(super) struct Cut {
    /// Its topic (as sent; lossy if not UTF-8).
    pub(super) topic: String,
    /// Its whole size on the wire, bytes.
    pub(super) bytes: u64,
    /// The broker sent it as a retained message.
    pub(super) retained: bool,
}

/// MQTT's control packet type of a PUBLISH (the fixed header's high nibble).
const PUBLISH: u8 = 3;

/// Where the filter is in the stream.
#[derive(Debug)]
enum State {
    /// Reading a fixed header: its bytes so far.
    Header(Vec<u8>),
    /// Passing this many more bytes of the current packet.
    Pass(u64),
    /// An oversized PUBLISH: its first byte, its remaining length, its
    /// whole size, and its variable header so far.
    Head {
        first: u8,
        remaining: u64,
        bytes: u64,
        head: Vec<u8>,
    },
    /// Skipping this many more bytes of a cut PUBLISH's payload.
    Skip(u64),
    /// A fixed header that is no MQTT: everything passes from here on
    /// (the client then says what is wrong).
    Raw,
}

/// The filter of one connection.
#[derive(Debug)]
pub(super) struct Filter {
    limit: u64,
    state: State,
}

impl Filter {
    /// PUBLISH packets above `limit` bytes (the whole packet) are cut.
    pub(super) fn new(limit: u64) -> Self {
        Filter {
            limit,
            state: State::Header(Vec::with_capacity(5)),
        }
    }

    /// Takes `input`, the next bytes from the broker: appends what goes
    /// on to `out`, and returns the messages cut.
    pub(super) fn feed(&mut self, mut input: &[u8], out: &mut Vec<u8>) -> Vec<Cut> {
        let mut cut = Vec::new();
        while !input.is_empty() {
            match &mut self.state {
                State::Raw => {
                    out.extend_from_slice(input);
                    input = &[];
                }
                State::Pass(left) => {
                    let n = take(*left, input.len());
                    out.extend_from_slice(&input[..n]);
                    input = &input[n..];
                    *left -= n as u64;
                    if *left == 0 {
                        self.state = State::Header(Vec::with_capacity(5));
                    }
                }
                State::Skip(left) => {
                    let n = take(*left, input.len());
                    input = &input[n..];
                    *left -= n as u64;
                    if *left == 0 {
                        self.state = State::Header(Vec::with_capacity(5));
                    }
                }
                State::Header(header) => {
                    header.push(input[0]);
                    input = &input[1..];
                    match remaining_length(&header[1..]) {
                        Length::More => {}
                        Length::Invalid => {
                            out.extend_from_slice(header);
                            self.state = State::Raw;
                        }
                        Length::Is(remaining) => {
                            let first = header[0];
                            let bytes = header.len() as u64 + remaining;
                            if first >> 4 == PUBLISH && bytes > self.limit {
                                self.state = State::Head {
                                    first,
                                    remaining,
                                    bytes,
                                    head: Vec::new(),
                                };
                            } else {
                                out.extend_from_slice(header);
                                self.state = if remaining == 0 {
                                    State::Header(Vec::with_capacity(5))
                                } else {
                                    State::Pass(remaining)
                                };
                            }
                        }
                    }
                }
                State::Head {
                    first,
                    remaining,
                    bytes,
                    head,
                } => {
                    if head.len() < 2 {
                        let n = take(2 - head.len() as u64, input.len());
                        head.extend_from_slice(&input[..n]);
                        input = &input[n..];
                        if head.len() < 2 {
                            continue;
                        }
                    }
                    let wanted = head_length(*first, head);
                    if wanted as u64 > *remaining {
                        // A topic longer than its packet: not MQTT.
                        out.push(*first);
                        out.extend_from_slice(&encode_length(*remaining));
                        out.extend_from_slice(head);
                        self.state = State::Raw;
                        continue;
                    }
                    if head.len() < wanted {
                        let n = take((wanted - head.len()) as u64, input.len());
                        head.extend_from_slice(&input[..n]);
                        input = &input[n..];
                        if head.len() < wanted {
                            continue;
                        }
                    }
                    let topic_len = usize::from(u16::from_be_bytes([head[0], head[1]]));
                    cut.push(Cut {
                        topic: String::from_utf8_lossy(&head[2..2 + topic_len]).into_owned(),
                        bytes: *bytes,
                        retained: *first & 1 == 1,
                    });
                    out.push(*first);
                    out.extend_from_slice(&encode_length(wanted as u64));
                    out.extend_from_slice(head);
                    let rest = *remaining - wanted as u64;
                    self.state = if rest == 0 {
                        State::Header(Vec::with_capacity(5))
                    } else {
                        State::Skip(rest)
                    };
                }
            }
        }
        cut
    }
}

/// The length of a PUBLISH's variable header (topic, and packet id above
/// QoS 0), from its first two bytes (the topic's length).
fn head_length(first: u8, head: &[u8]) -> usize {
    let topic = usize::from(u16::from_be_bytes([head[0], head[1]]));
    let qos = (first >> 1) & 3;
    2 + topic + if qos > 0 { 2 } else { 0 }
}

/// How many of `available` bytes to take when `left` are wanted.
fn take(left: u64, available: usize) -> usize {
    usize::try_from(left).map_or(available, |l| l.min(available))
}

/// A remaining length being read.
#[derive(Debug, PartialEq, Eq)]
enum Length {
    /// Its bytes so far end with a continuation bit.
    More,
    /// More than four bytes: no MQTT.
    Invalid,
    /// Complete.
    Is(u64),
}

/// MQTT's variable-length integer in `bytes` (1 to 4 bytes, 7 bits each,
/// least significant first).
fn remaining_length(bytes: &[u8]) -> Length {
    let mut value = 0u64;
    for (i, b) in bytes.iter().enumerate() {
        if i == 4 {
            return Length::Invalid;
        }
        value |= u64::from(b & 0x7f) << (7 * i);
        if b & 0x80 == 0 {
            return Length::Is(value);
        }
    }
    if bytes.len() >= 4 {
        Length::Invalid
    } else {
        Length::More
    }
}

/// `value` as MQTT's variable-length integer.
fn encode_length(mut value: u64) -> Vec<u8> {
    let mut out = Vec::with_capacity(4);
    loop {
        let mut b = (value & 0x7f) as u8;
        value >>= 7;
        if value > 0 {
            b |= 0x80;
        }
        out.push(b);
        if value == 0 {
            return out;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A PUBLISH: QoS, retain, topic, packet id (QoS > 0), payload.
    fn publish(qos: u8, retain: bool, topic: &str, payload: &[u8]) -> Vec<u8> {
        let mut body = Vec::new();
        body.extend_from_slice(&(topic.len() as u16).to_be_bytes());
        body.extend_from_slice(topic.as_bytes());
        if qos > 0 {
            body.extend_from_slice(&7u16.to_be_bytes());
        }
        body.extend_from_slice(payload);
        let mut p = vec![(PUBLISH << 4) | (qos << 1) | u8::from(retain)];
        p.extend_from_slice(&encode_length(body.len() as u64));
        p.extend_from_slice(&body);
        p
    }

    /// `input` through a filter of `limit` in chunks of `chunk` bytes.
    fn run(limit: u64, input: &[u8], chunk: usize) -> (Vec<u8>, Vec<Cut>) {
        let mut f = Filter::new(limit);
        let mut out = Vec::new();
        let mut cut = Vec::new();
        for part in input.chunks(chunk) {
            cut.extend(f.feed(part, &mut out));
        }
        (out, cut)
    }

    #[test]
    fn lengths_round_trip() {
        for v in [
            0,
            1,
            127,
            128,
            16_383,
            16_384,
            2_097_151,
            2_097_152,
            268_435_455,
        ] {
            let e = encode_length(v);
            assert_eq!(remaining_length(&e), Length::Is(v), "{v}");
        }
        assert_eq!(remaining_length(&[0x80]), Length::More);
        assert_eq!(remaining_length(&[0x80, 0x80, 0x80, 0x80]), Length::Invalid);
    }

    #[test]
    fn small_packets_pass_unchanged_in_any_chunks() {
        // CONNACK, SUBACK, a PUBLISH at QoS 1, PINGRESP.
        let mut stream = vec![0x20, 0x02, 0x00, 0x00, 0x90, 0x03, 0x00, 0x01, 0x01];
        stream.extend(publish(1, false, "spBv1.0/g/DCMD/n/d", b"payload"));
        stream.extend([0xd0, 0x00]);
        for chunk in [1, 2, 3, 7, 1000] {
            let (out, cut) = run(64, &stream, chunk);
            assert_eq!(out, stream, "chunk {chunk}");
            assert!(cut.is_empty());
        }
    }

    #[test]
    fn a_publish_over_the_limit_goes_on_empty_with_its_flags_topic_and_packet_id() {
        let big = publish(1, true, "spBv1.0/g/DCMD/n/conveyor", &vec![b'x'; 400_000]);
        let after = publish(0, false, "spBv1.0/STATE/scada", b"{}");
        let mut stream = big.clone();
        stream.extend_from_slice(&after);
        for chunk in [1, 5, 4096, 1 << 20] {
            let (out, cut) = run(65_536, &stream, chunk);
            let mut expected = publish(1, true, "spBv1.0/g/DCMD/n/conveyor", b"");
            expected.extend_from_slice(&after);
            assert_eq!(out, expected, "chunk {chunk}");
            assert_eq!(
                cut,
                vec![Cut {
                    topic: "spBv1.0/g/DCMD/n/conveyor".into(),
                    bytes: big.len() as u64,
                    retained: true,
                }]
            );
        }
    }

    #[test]
    fn the_limit_is_the_whole_packet() {
        let p = publish(0, false, "t", &[0; 100]);
        let size = p.len() as u64;
        assert!(run(size, &p, 3).1.is_empty());
        assert_eq!(run(size - 1, &p, 3).1.len(), 1);
        // QoS 0: no packet id kept.
        assert_eq!(run(size - 1, &p, 3).0, publish(0, false, "t", b""));
    }

    #[test]
    fn what_is_not_mqtt_passes_for_the_client_to_refuse() {
        // A remaining length of five bytes.
        let junk = [0x30, 0xff, 0xff, 0xff, 0xff, 0x7f, 1, 2, 3];
        assert_eq!(run(16, &junk, 2).0, junk);
        // A topic longer than its packet.
        let mut lie = vec![PUBLISH << 4, 0x7f, 0xff, 0xff];
        lie.extend([0u8; 10]);
        let (out, cut) = run(16, &lie, 1);
        assert!(cut.is_empty());
        assert_eq!(out, lie);
    }
}
