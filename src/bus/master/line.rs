//! The line's own I/O for the master: silences, one frame out, one reply
//! in (framed by length, or by silence), the guard after a fault.

use std::io;
use std::time::{Duration, Instant};

use super::{DELIVERY_ALLOWANCE, Fault, RtuMaster};
use crate::bus::port::Direction;
use crate::modbus::rtu_frame::{self, FrameLength};

impl RtuMaster {
    /// Waits until the line has been silent for `gap` (less `early`),
    /// discarding (and counting) whatever arrives meanwhile; every byte
    /// restarts the silence. `precise`: never before that moment (the frame
    /// goes out then); else about then, as the timer wakes (the job is
    /// picked then, just before the silence ends).
    pub(super) async fn wait_for_silence(
        &mut self,
        gap: Duration,
        early: Duration,
        precise: bool,
    ) -> io::Result<()> {
        // A line that never goes quiet (a babbling device) must not stall the
        // bus forever: after this long we send anyway, and the reply check
        // sorts out the rest. Counted from the end of a broadcast's
        // turnaround, which even a babbling line does not cut short.
        let give_up = self.quiet_since.max(Instant::now())
            + self
                .settings
                .response_timeout
                .max(Duration::from_millis(50));
        let mut woke = false;
        loop {
            let deadline = self.quiet_since + gap.saturating_sub(early);
            let now = Instant::now();
            if now >= deadline || woke {
                // Bytes that arrived but were not read yet (while we were
                // busy elsewhere, or as the timer woke us) are stray too,
                // and the silence starts again after them.
                if self.drain_input()? == 0 || now >= give_up {
                    break;
                }
                self.quiet_since = self.quiet_since.max(Instant::now());
                woke = false;
                continue;
            }
            tokio::select! {
                biased;
                read = self.port.read(&mut self.buf[..]) => {
                    let n = self.got(read)?;
                    self.stray += n;
                    self.tap.stray(&self.buf[..n], Instant::now());
                    // The silence restarts now, unless it was set to end
                    // later (a broadcast's turnaround): a stray byte must
                    // not cut the drives' time to act short.
                    let now = Instant::now();
                    self.quiet_since = self.quiet_since.max(now);
                    if now >= give_up {
                        break;
                    }
                }
                slept = async {
                    if precise {
                        self.timer.sleep_until(deadline).await
                    } else {
                        self.timer.sleep_until_near(deadline).await
                    }
                } => {
                    slept?;
                    woke = true;
                }
            }
        }
        Ok(())
    }

    /// Reads and discards what has arrived, without waiting; the count.
    pub(super) fn drain_input(&mut self) -> io::Result<usize> {
        let mut drained = 0;
        loop {
            match self.port.try_read(&mut self.buf[..]) {
                Ok(0) => return Err(self.port.closed()),
                Ok(n) => {
                    drained += n;
                    self.tap.stray(&self.buf[..n], Instant::now());
                }
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => break,
                Err(e) => return Err(e),
            }
        }
        self.stray += drained;
        Ok(drained)
    }

    /// Puts one frame on the wire in one write; returns when it started.
    /// Sets `sent` as soon as the port has taken a byte of it.
    pub(super) async fn send(&mut self, frame: &[u8], sent: &mut bool) -> io::Result<Instant> {
        let rs485 = self.settings.rs485;
        if rs485.direction == Direction::Rts {
            self.port.set_rts(rs485.rts_active_high)?;
            if !rs485.before().is_zero() {
                self.timer
                    .sleep_until(Instant::now() + rs485.before())
                    .await?;
            }
        }
        let sent_at = Instant::now();
        // write_all, counting: an error after a partial write must not pass
        // for a request that never left.
        let mut written = 0;
        while written < frame.len() {
            match self.port.write(&frame[written..]).await? {
                0 => return Err(io::ErrorKind::WriteZero.into()),
                n => {
                    written += n;
                    *sent = true;
                }
            }
        }
        // No flush: nothing is buffered above the port, and a serial port's
        // flush is tcdrain(3), which would hold this thread until the UART
        // has sent the frame (and a tick of the kernel's clock after it).
        if rs485.direction == Direction::Rts {
            // The bus thread is ours: blocking until the UART is empty is the
            // exact moment to release the line.
            self.port.drain()?;
            if !rs485.after().is_zero() {
                self.timer
                    .sleep_until(Instant::now() + rs485.after())
                    .await?;
            }
            self.port.set_rts(!rs485.rts_active_high)?;
        }
        Ok(sent_at)
    }

    /// Reads one reply frame to `request` into `buf`; `Ok(Err(fault))` for a
    /// protocol fault, `Err` for a port failure; with the instant its first
    /// byte was read.
    ///
    /// `first_byte_by` is the wait for the reply's first byte. Once bytes
    /// flow, the deadline follows the wire: the bytes still to come at the
    /// character time, plus t3.5 and the [`DELIVERY_ALLOWANCE`], counted
    /// from the last bytes received, but never earlier than the timeout. A
    /// 125-register reply takes 265 ms at 9600 baud; a drive that starts it
    /// in time gets it through whatever the timeout.
    ///
    /// A whole frame from another unit is a late reply to an earlier
    /// request: it is discarded as stray bytes and the wait goes on, moved
    /// by the time that frame held the line, but never past `latest`.
    pub(super) async fn receive(
        &mut self,
        unit: u8,
        request: &[u8],
        first_byte_by: Instant,
        latest: Instant,
    ) -> io::Result<(Result<usize, Fault>, Option<Instant>)> {
        let line = self.settings.line;
        let t35 = line.t3_5();
        let expected = rtu_frame::expected_response_length(request).unwrap_or(rtu_frame::MAX_FRAME);
        let mut len = 0;
        let mut last_byte = Instant::now();
        let mut first_byte = None;
        let mut first_byte_by = first_byte_by;
        let mut deadline = first_byte_by;
        loop {
            // A full buffer holds no Modbus frame (the longest is 256 bytes):
            // it is noise. Reading on would read into an empty slice, whose
            // Ok(0) means an unplugged adapter.
            if len >= self.buf.len() {
                self.quiet_since = last_byte;
                return Ok((
                    Err(Fault::Mismatch("reply longer than any Modbus frame")),
                    first_byte,
                ));
            }
            let complete = match rtu_frame::response_length(&self.buf[..len]) {
                FrameLength::Known(n) if len >= n => Some(n),
                FrameLength::Known(_) | FrameLength::NeedMore => None,
                FrameLength::BySilence => match self.more_or_silence(len, last_byte).await? {
                    Some(n) => {
                        len += n;
                        last_byte = Instant::now();
                        continue;
                    }
                    None => Some(len),
                },
            };
            if let Some(n) = complete {
                self.quiet_since = last_byte;
                if self.buf[0] == unit || last_byte >= latest {
                    return Ok((Ok(n), first_byte));
                }
                // Another unit's late reply: never ours. Discard it and wait
                // on, as long again as it held the line.
                self.stray += n;
                self.tap.stray(&self.buf[..n], last_byte);
                let held = first_byte.map_or(Duration::ZERO, |t| last_byte - t);
                self.buf.copy_within(n..len, 0);
                len -= n;
                first_byte = None;
                first_byte_by = (first_byte_by + held + t35).min(latest);
                deadline = first_byte_by;
                if len > 0 {
                    first_byte = Some(last_byte);
                }
                continue;
            }
            let need = match rtu_frame::response_length(&self.buf[..len]) {
                FrameLength::Known(n) => Some(n),
                _ => None,
            };
            if len > 0 {
                let remaining = if self.buf[0] == unit {
                    need.unwrap_or(expected)
                } else {
                    need.unwrap_or(rtu_frame::MAX_FRAME)
                }
                .saturating_sub(len);
                deadline =
                    deadline.max(last_byte + line.wire_time(remaining) + t35 + DELIVERY_ALLOWANCE);
            }
            let end = need.map_or(self.buf.len(), |n| n.min(self.buf.len()));
            match tokio::time::timeout_at(deadline.into(), self.port.read(&mut self.buf[len..end]))
                .await
            {
                Ok(read) => {
                    len += self.got(read)?;
                    last_byte = Instant::now();
                    first_byte.get_or_insert(last_byte);
                }
                Err(_) if len == 0 => return Ok((Err(Fault::Timeout), None)),
                Err(_) => {
                    self.quiet_since = last_byte;
                    let fault = if self.buf[0] == unit {
                        Fault::Mismatch("reply cut short")
                    } else {
                        Fault::Mismatch("reply from another unit")
                    };
                    return Ok((Err(fault), first_byte));
                }
            }
        }
    }

    /// For a frame whose length is unknown, read from `buf[len]` on: the
    /// bytes that came, or `None` once the line was silent for t3.5 after
    /// `last_byte` (the frame ended).
    async fn more_or_silence(
        &mut self,
        len: usize,
        last_byte: Instant,
    ) -> io::Result<Option<usize>> {
        let t35 = self.settings.line.t3_5();
        tokio::select! {
            biased;
            read = self.port.read(&mut self.buf[len..]) => Ok(Some(self.got(read)?)),
            slept = self.timer.sleep_until_relaxed(last_byte + t35) => slept.map(|()| None),
        }
    }

    /// After a fault: keep the line for `time`, discarding anything that
    /// arrives (a late reply), then flush the input.
    pub(super) async fn guard(&mut self, time: Duration) -> io::Result<()> {
        let until = Instant::now() + time;
        loop {
            tokio::select! {
                read = self.port.read(&mut self.buf[..]) => {
                    let n = self.got(read)?;
                    self.stray += n;
                    self.tap.stray(&self.buf[..n], Instant::now());
                }
                slept = self.timer.sleep_until_relaxed(until) => {
                    slept?;
                    break;
                }
            }
        }
        self.flush_input()
    }

    /// Discards whatever the port holds unread; the line is silent from now.
    pub(super) fn flush_input(&mut self) -> io::Result<()> {
        self.port.clear_input()?;
        self.quiet_since = Instant::now();
        Ok(())
    }

    /// A read's byte count; a read of 0 bytes means the line went away (the
    /// adapter was unplugged, the device server closed the connection).
    pub(super) fn got(&self, read: io::Result<usize>) -> io::Result<usize> {
        match read {
            Ok(0) => Err(self.port.closed()),
            other => other,
        }
    }
}
