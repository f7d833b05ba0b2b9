//! Progress bars on stderr for long work (`indicatif`; drawn only when
//! stderr is a terminal, so logs and tests stay clean).

use indicatif::{ProgressBar, ProgressStyle};
use nebel_scene::reference::ReferenceProgress;

/// A bar of `length` steps labelled `what`, or a hidden one when `shown` is
/// false.
pub fn bar(shown: bool, what: &str, length: u64) -> ProgressBar {
    let bar = if shown {
        ProgressBar::new(length)
    } else {
        ProgressBar::hidden()
    };
    bar.set_style(
        ProgressStyle::with_template(&format!(
            "nebel: {what} {{pos}}/{{len}} {{wide_bar}} {{elapsed}} (ETA {{eta}})"
        ))
        .expect("a valid template"),
    );
    bar
}

/// A bar over the rows of every pass of an exact reference, and the
/// callback that moves it.
pub fn reference_bar(shown: bool) -> (ProgressBar, impl Fn(ReferenceProgress) + Sync) {
    let bar = bar(shown, "reference row", 0);
    let moved = bar.clone();
    let report = move |progress: ReferenceProgress| {
        let total = u64::from(progress.rows_total);
        moved.set_length(total * progress.passes as u64);
        moved.set_position(total * progress.pass as u64 + u64::from(progress.rows_done));
    };
    (bar, report)
}
