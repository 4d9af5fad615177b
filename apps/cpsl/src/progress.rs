//! Progress bars drawn from the library's typed progress events.

use cpsl_core::{Progress, ProgressEvent};
use indicatif::{ProgressBar, ProgressStyle};
use std::sync::Mutex;

/// Draws one indicatif bar per stage; warnings go to stderr above the bar.
#[derive(Default)]
pub struct Bars {
    bar: Mutex<Option<ProgressBar>>,
}

impl Progress for Bars {
    fn event(&self, event: ProgressEvent<'_>) {
        let mut slot = self.bar.lock().expect("progress lock");
        match event {
            ProgressEvent::Start { stage, total } => {
                let bar = match total {
                    Some(n) => ProgressBar::new(n).with_style(
                        ProgressStyle::with_template(
                            "{msg:>16} [{bar:30}] {pos}/{len} {elapsed} eta {eta}",
                        )
                        .expect("template")
                        .progress_chars("=> "),
                    ),
                    None => ProgressBar::new_spinner(),
                };
                bar.set_message(stage.to_string());
                *slot = Some(bar);
            }
            ProgressEvent::Advance { done, .. } => {
                if let Some(b) = slot.as_ref() {
                    b.set_position(done);
                }
            }
            ProgressEvent::Finish { .. } => {
                if let Some(b) = slot.take() {
                    b.finish_and_clear();
                }
            }
            ProgressEvent::Warning { message } => match slot.as_ref() {
                Some(b) => b.println(format!("warning: {message}")),
                None => eprintln!("warning: {message}"),
            },
        }
    }
}
