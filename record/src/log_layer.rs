//! A `tracing` layer that records log lines as `foxglove.Log` on `/log`.
//!
//! ```text
//! let tap = amr_record::LogTap::default();
//! tracing_subscriber::registry().with(fmt_layer).with(amr_record::LogLayer::new(tap.clone())).init();
//! // later: RecordSources { logs: Some(tap), .. }
//! ```

use std::fmt::Write as _;

use tracing::field::{Field, Visit};
use tracing_subscriber::layer::Context;

use crate::encode::{Event, LogLine};
use crate::foxglove::Level;
use crate::recorder::LogTap;

/// Sends every event it sees (after the subscriber's filters) to the running recorder, if any.
#[derive(Debug, Clone)]
pub struct LogLayer {
    tap: LogTap,
}

impl LogLayer {
    #[must_use]
    pub fn new(tap: LogTap) -> Self {
        LogLayer { tap }
    }
}

/// The `message` field, then the others as ` key=value`.
#[derive(Default)]
struct Text {
    message: String,
    fields: String,
}

impl Visit for Text {
    fn record_str(&mut self, field: &Field, value: &str) {
        if field.name() == "message" {
            self.message.push_str(value);
        } else {
            let _ = write!(self.fields, " {}={}", field.name(), value);
        }
    }

    fn record_debug(&mut self, field: &Field, value: &dyn std::fmt::Debug) {
        if field.name() == "message" {
            let _ = write!(self.message, "{value:?}");
        } else {
            let _ = write!(self.fields, " {}={:?}", field.name(), value);
        }
    }
}

impl<S: tracing::Subscriber> tracing_subscriber::Layer<S> for LogLayer {
    fn on_event(&self, event: &tracing::Event<'_>, _ctx: Context<'_, S>) {
        let meta = event.metadata();
        let level = match *meta.level() {
            tracing::Level::ERROR => Level::Error,
            tracing::Level::WARN => Level::Warning,
            tracing::Level::INFO => Level::Info,
            tracing::Level::DEBUG | tracing::Level::TRACE => Level::Debug,
        };
        let mut text = Text::default();
        event.record(&mut text);
        self.tap.send(Event::Log(LogLine {
            level,
            name: meta.target().to_owned(),
            message: text.message + &text.fields,
            file: meta.file().unwrap_or_default().to_owned(),
            line: meta.line().unwrap_or(0),
        }));
    }
}
