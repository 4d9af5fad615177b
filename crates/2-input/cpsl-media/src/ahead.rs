//! Reading ahead: a source's frames decoded on a thread of their own, a few frames before the
//! caller asks for them, so that decoding overlaps the caller's work on the frame before.

use crate::{open_with, FrameSource, Info, InputFrame, MediaError};
use std::path::Path;
use std::sync::mpsc::{sync_channel, Receiver};
use std::thread::JoinHandle;

/// One frame's outcome and the damaged packets skipped up to it.
type Message = (Result<Option<InputFrame>, MediaError>, usize);

/// A [`FrameSource`] whose frames are decoded on a thread of their own (see [`open_ahead`]).
pub struct ReadAhead {
    info: Info,
    /// `None` once the end or an error was handed on.
    frames: Option<Receiver<Message>>,
    thread: Option<JoinHandle<()>>,
}

/// [`open_with`] on a thread of its own that decodes up to `ahead` frames (at least one)
/// before they are asked for. The same frames, errors and [`Info`] as [`open_with`], in the
/// same order (`Info::damaged` counts the packets skipped up to the last frame handed on).
pub fn open_ahead(path: &Path, motion: bool, ahead: usize) -> Result<ReadAhead, MediaError> {
    let (opened_tx, opened) = sync_channel::<Result<Info, MediaError>>(1);
    // The thread decodes the next frame while the channel holds the rest.
    let (frames_tx, frames) = sync_channel::<Message>(ahead.max(1) - 1);
    let owned = path.to_path_buf();
    let thread = std::thread::Builder::new()
        .name("cpsl-decode".into())
        .spawn(move || {
            let mut src = match open_with(&owned, motion) {
                Ok(s) => s,
                Err(e) => {
                    let _ = opened_tx.send(Err(e));
                    return;
                }
            };
            if opened_tx.send(Ok(src.info().clone())).is_err() {
                return;
            }
            loop {
                let next = src.next_frame();
                let last = !matches!(next, Ok(Some(_)));
                // A send fails once the reader is dropped: nothing more is wanted.
                if frames_tx.send((next, src.info().damaged)).is_err() || last {
                    return;
                }
            }
        })
        .map_err(|e| MediaError::Unreadable {
            path: path.to_path_buf(),
            reason: format!("starting a decoding thread: {e}"),
        })?;
    match opened.recv() {
        Ok(Ok(info)) => Ok(ReadAhead {
            info,
            frames: Some(frames),
            thread: Some(thread),
        }),
        Ok(Err(e)) => {
            let _ = thread.join();
            Err(e)
        }
        Err(_) => rethrow(thread),
    }
}

/// Joins a decoding thread that hung up without a word: it panicked, and so does the caller.
fn rethrow(thread: JoinHandle<()>) -> ! {
    match thread.join() {
        Err(panic) => std::panic::resume_unwind(panic),
        Ok(()) => panic!("the decoding thread ended without handing on its frames"),
    }
}

impl FrameSource for ReadAhead {
    fn info(&self) -> &Info {
        &self.info
    }

    fn next_frame(&mut self) -> Result<Option<InputFrame>, MediaError> {
        let Some(frames) = &self.frames else {
            return Ok(None);
        };
        match frames.recv() {
            Ok((next, damaged)) => {
                self.info.damaged = damaged;
                if !matches!(next, Ok(Some(_))) {
                    self.frames = None;
                }
                next
            }
            Err(_) => {
                self.frames = None;
                rethrow(
                    self.thread
                        .take()
                        .expect("the decoding thread is joined once"),
                )
            }
        }
    }
}

impl Drop for ReadAhead {
    fn drop(&mut self) {
        // Hanging up first ends a thread waiting to hand on a frame.
        self.frames = None;
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}
