//! How the one-shot commands (`bake`, `submit`, `bench`, …) show the engine's log: a
//! warning or an error reads `warning: …` / `error: …`, the way the command's own
//! messages and the importer's warnings read, with no timestamp or module path.
//!
//! Why: the engine reports what a user should act on (a level whose generated UVs are
//! mostly padding, a software GPU adapter) through `tracing`, because the service's
//! workers log the same events with the job's fields. The default `fmt` layout, made for
//! logs, put those lines among the command's `warning:` lines with a timestamp and a
//! target, so the same kind of advice looked like two kinds. Lower levels, shown only when
//! `RUST_LOG` asks for them, keep the full log layout: they are for a developer. The
//! service (`serve`, `worker`) keeps the log layout throughout.
//!
//! The event's fields follow its message as `key=value`, as `fmt` writes them.
//!
//! While a bake draws its progress bar on a terminal, each log line is written with the
//! bar lifted ([`Stderr`], indicatif's `suspend`): a warning written beside a bar that
//! redraws itself four times a second otherwise lands in the middle of the bar's line.

use std::fmt;
use std::io::Write;
use std::sync::Mutex;

use indicatif::ProgressBar;

use tracing::{Event, Level, Subscriber};
use tracing_subscriber::fmt::format::{Format, Writer};
use tracing_subscriber::fmt::{FmtContext, FormatEvent, FormatFields};
use tracing_subscriber::registry::LookupSpan;

/// `warning:` / `error:` lines for WARN and ERROR; the full layout below them.
pub struct CommandLine {
    full: Format,
}

impl CommandLine {
    pub fn new(ansi: bool) -> Self {
        Self {
            full: Format::default().with_ansi(ansi),
        }
    }
}

impl<S, N> FormatEvent<S, N> for CommandLine
where
    S: Subscriber + for<'a> LookupSpan<'a>,
    N: for<'a> FormatFields<'a> + 'static,
{
    fn format_event(&self, ctx: &FmtContext<'_, S, N>, mut writer: Writer<'_>, event: &Event<'_>) -> fmt::Result {
        let prefix = match *event.metadata().level() {
            Level::ERROR => "error",
            Level::WARN => "warning",
            _ => return self.full.format_event(ctx, writer, event),
        };
        write!(writer, "{prefix}: ")?;
        ctx.field_format().format_fields(writer.by_ref(), event)?;
        writeln!(writer)
    }
}

/// The progress bar on the terminal now, if any (`show_above`).
static BAR: Mutex<Option<ProgressBar>> = Mutex::new(None);

/// Log lines go above `bar` until it is finished (a hidden bar changes nothing).
pub fn show_above(bar: &ProgressBar) {
    if let Ok(mut b) = BAR.lock() {
        *b = Some(bar.clone());
    }
}

/// stderr, with the registered progress bar lifted around each write (the `fmt` layer
/// writes a whole event in one call).
pub struct Stderr;

impl Write for Stderr {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let bar = BAR
            .lock()
            .ok()
            .and_then(|b| b.clone())
            .filter(|b| !b.is_hidden() && !b.is_finished());
        match bar {
            Some(bar) => bar.suspend(|| std::io::stderr().write_all(buf))?,
            None => std::io::stderr().write_all(buf)?,
        }
        Ok(buf.len())
    }

    fn flush(&mut self) -> std::io::Result<()> {
        std::io::stderr().flush()
    }
}
