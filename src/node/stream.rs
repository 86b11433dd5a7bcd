//! The network source: camera frames over TCP in the [`crate::io::hcap`] record format.
//!
//! A camera driver (in another process or on another machine) connects and writes one
//! frame record per frame ([`StreamSender`] is that side, used by tests and tools). The node
//! listens ([`StreamReceiver`]), accepts one connection at a time, and decodes records as
//! bytes arrive; malformed records are counted and dropped and the stream goes on. TCP keeps
//! the order and delivers whole clouds (a 848x480 cloud is 4.9 MB, far beyond one UDP
//! datagram).

use crate::camera::Frame;
use crate::io::hcap::{self, Decoder, RecordKind, WireError};
use std::io::{self, Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream, ToSocketAddrs};
use std::time::{Duration, Instant};

/// Sends camera frames to a node.
pub struct StreamSender {
    stream: TcpStream,
    buf: Vec<u8>,
}

impl StreamSender {
    pub fn connect(addr: impl ToSocketAddrs) -> io::Result<Self> {
        let stream = TcpStream::connect(addr)?;
        stream.set_nodelay(true)?;
        Ok(Self {
            stream,
            buf: Vec::new(),
        })
    }

    pub fn send(&mut self, frame: &Frame) -> io::Result<()> {
        self.buf.clear();
        hcap::write_record(&mut self.buf, RecordKind::Frame, &hcap::encode_frame(frame));
        self.stream.write_all(&self.buf)
    }

    /// Writes raw bytes (tests use it to inject corrupt records).
    pub fn send_raw(&mut self, bytes: &[u8]) -> io::Result<()> {
        self.stream.write_all(bytes)
    }
}

/// What the receiver saw so far.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct StreamCounters {
    pub frames: u64,
    /// Records dropped: bad header, CRC mismatch, unparsable payload, wrong kind.
    pub malformed: u64,
    pub connections: u64,
}

/// Receives camera frames on a TCP port.
pub struct StreamReceiver {
    listener: TcpListener,
    conn: Option<TcpStream>,
    decoder: Decoder,
    bad_payloads: u64,
    counters: StreamCounters,
    chunk: Vec<u8>,
}

impl StreamReceiver {
    /// Listens on `addr` (port 0 picks a free port: see [`StreamReceiver::local_addr`]).
    pub fn bind(addr: impl ToSocketAddrs) -> io::Result<Self> {
        Ok(Self {
            listener: TcpListener::bind(addr)?,
            conn: None,
            decoder: Decoder::new(),
            bad_payloads: 0,
            counters: StreamCounters::default(),
            chunk: vec![0; 1 << 16],
        })
    }

    pub fn local_addr(&self) -> io::Result<SocketAddr> {
        self.listener.local_addr()
    }

    pub fn counters(&self) -> StreamCounters {
        StreamCounters {
            malformed: self.decoder.malformed + self.bad_payloads,
            ..self.counters
        }
    }

    /// Waits at most `timeout` for a sender to connect (never blocks longer, so the node
    /// can stop).
    fn accept(&mut self, timeout: Duration) -> io::Result<bool> {
        let until = Instant::now() + timeout;
        self.listener.set_nonblocking(true)?;
        loop {
            match self.listener.accept() {
                Ok((c, _)) => {
                    c.set_nonblocking(false)?;
                    c.set_read_timeout(Some(timeout.max(Duration::from_millis(1))))?;
                    self.counters.connections += 1;
                    self.decoder = Decoder::new();
                    self.conn = Some(c);
                    return Ok(true);
                }
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => {
                    if Instant::now() >= until {
                        return Ok(false);
                    }
                    std::thread::sleep(Duration::from_millis(2));
                }
                Err(e) => return Err(e),
            }
        }
    }

    /// The next frame, waiting at most `timeout` for bytes; `Ok(None)` on timeout or when
    /// the sender closed (the receiver then waits for the next connection).
    pub fn recv(&mut self, timeout: Duration) -> io::Result<Option<Frame>> {
        loop {
            while let Some(record) = self.decoder.next_record() {
                match record.kind {
                    RecordKind::Frame => match hcap::decode_frame(&record.payload) {
                        Ok(frame) => {
                            self.counters.frames += 1;
                            return Ok(Some(frame));
                        }
                        Err(_) => self.bad_payloads += 1,
                    },
                    _ => self
                        .decoder
                        .count_bad_payload(WireError::Kind(record.kind as u16)),
                }
            }
            if self.conn.is_none() && !self.accept(timeout)? {
                return Ok(None);
            }
            let Some(conn) = self.conn.as_mut() else {
                return Ok(None);
            };
            match conn.read(&mut self.chunk) {
                Ok(0) => {
                    self.conn = None;
                    return Ok(None);
                }
                Ok(n) => self.decoder.feed(&self.chunk[..n]),
                Err(e)
                    if matches!(
                        e.kind(),
                        io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut
                    ) =>
                {
                    return Ok(None);
                }
                Err(e) => return Err(e),
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::hcap::tests::test_frame;

    #[test]
    fn frames_cross_tcp_and_malformed_records_are_counted() {
        let mut receiver = StreamReceiver::bind("127.0.0.1:0").unwrap();
        let addr = receiver.local_addr().unwrap();
        let sender = std::thread::spawn(move || {
            let mut s = StreamSender::connect(addr).unwrap();
            for i in 0..4 {
                s.send(&test_frame(i % 2, f64::from(i) * 0.033, 2000))
                    .unwrap();
                if i == 1 {
                    // A record with a corrupted payload, and one of the wrong kind.
                    let mut bad = Vec::new();
                    hcap::write_record(&mut bad, RecordKind::Frame, b"short");
                    hcap::write_record(&mut bad, RecordKind::Tick, b"not a frame");
                    let mut flipped = Vec::new();
                    hcap::write_record(
                        &mut flipped,
                        RecordKind::Frame,
                        &hcap::encode_frame(&test_frame(0, 9.0, 10)),
                    );
                    flipped[30] ^= 1;
                    bad.extend_from_slice(&flipped);
                    s.send_raw(&bad).unwrap();
                }
            }
        });
        let mut stamps = Vec::new();
        while stamps.len() < 4 {
            if let Some(f) = receiver.recv(Duration::from_secs(5)).unwrap() {
                assert_eq!(f.cloud.points.len(), 2000);
                stamps.push(f.stamp_s);
            }
        }
        sender.join().unwrap();
        assert_eq!(stamps, vec![0.0, 0.033, 0.066, 0.099]);
        let c = receiver.counters();
        assert_eq!((c.frames, c.malformed, c.connections), (4, 3, 1));
    }
}
