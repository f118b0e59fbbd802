//! The supervising surgeon at this terminal: commands typed on standard input, one a line,
//! and the interventions the robot asks for answered there.

use std::io::BufRead;
use std::sync::mpsc::{Receiver, Sender, TryRecvError};
use stitch_engine::{
    CheckpointRequest, InterventionRequest, InterventionResult, LIVE_POLL, Moment, NextPoll,
    Refusal, Supervisor, SupervisorCommand,
};

/// A line heard, and who said it (`terminal`, `console viewer 3 (127.0.0.1:50412)`).
pub type Heard = (String, String);

/// What the surgeon types: `pause`, `resume`, `abort`, `e-stop`, `take-over`, `hand-back`
/// at any time (acted on at once, in the middle of a motion too: the engine asks every
/// [`LIVE_POLL`]), `done` or `failed` to end an intervention, and `go` to confirm a plan's
/// checkpoint.
/// End of input (Ctrl-D, a closed pipe) while the run waits on the surgeon aborts it.
/// With the web console (`--console`), its buttons say the same words; the run's input ends
/// when both have.
pub struct ConsoleSupervisor {
    lines: Receiver<Heard>,
    say: Box<dyn FnMut(&str)>,
    /// Whether the end of input has been said (once, when first seen).
    closed_said: bool,
    /// Who said the last line.
    from: String,
    /// Commands the web console refused, for the journal.
    refusals: Option<Receiver<Refusal>>,
}

impl std::fmt::Debug for ConsoleSupervisor {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ConsoleSupervisor").finish_non_exhaustive()
    }
}

/// The commands, as the prompts list them.
const COMMANDS: &str = "pause, resume, abort, e-stop, take-over or hand-back";

/// Read standard input's lines into `tx` on a thread of their own, as the terminal's.
fn read_stdin(tx: Sender<Heard>) {
    std::thread::spawn(move || {
        let mut input = std::io::stdin().lock();
        let mut buf = Vec::new();
        loop {
            buf.clear();
            match input.read_until(b'\n', &mut buf) {
                Ok(0) => return,
                // A line that is not UTF-8 is read as well as it can be (and then said to be
                // unknown), not taken for the end of input.
                Ok(_) => {
                    let line = String::from_utf8_lossy(&buf).into_owned();
                    if tx.send((line, "terminal".to_string())).is_err() {
                        return;
                    }
                }
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => {
                    eprintln!("supervisor: cannot read standard input: {e}");
                    return;
                }
            }
        }
    });
}

impl ConsoleSupervisor {
    /// Read standard input on a thread of its own; speak on standard error.
    pub fn stdin() -> Self {
        let (tx, rx) = std::sync::mpsc::channel();
        read_stdin(tx);
        let mut me = Self::new(rx, Box::new(|s: &str| eprintln!("{s}")));
        (me.say)(&format!(
            "supervisor: you, at this terminal. Type {COMMANDS} and Enter at any time (acted \
             on at once, mid-motion too); Ctrl-C holds both arms and ends the run."
        ));
        me
    }

    /// Standard input and the web console's buttons, both heard; the console's refusals
    /// journaled.
    #[cfg(feature = "console")]
    pub fn stdin_and_web(feeds: crate::ConsoleFeeds) -> Self {
        read_stdin(feeds.sender);
        let mut me = Self::new(feeds.commands, Box::new(|s: &str| eprintln!("{s}")));
        me.refusals = Some(feeds.refusals);
        (me.say)(&format!(
            "supervisor: you, at this terminal or the web console's buttons. Type {COMMANDS} \
             and Enter at any time (acted on at once, mid-motion too); Ctrl-C holds both arms \
             and ends the run."
        ));
        me
    }

    /// A supervisor reading `lines` and speaking through `say` (tests drive it so).
    pub fn new(lines: Receiver<Heard>, say: Box<dyn FnMut(&str)>) -> Self {
        Self {
            lines,
            say,
            closed_said: false,
            from: "terminal".to_string(),
            refusals: None,
        }
    }

    /// The next line, waiting for it; `None` once every input has ended.
    fn next_line(&mut self) -> Option<String> {
        let (line, from) = self.lines.recv().ok()?;
        self.from = from;
        Some(line)
    }

    /// A typed line as a command, or `None` (said why) for an empty or unknown one.
    fn command(&mut self, line: &str) -> Option<SupervisorCommand> {
        let word = line.trim().to_ascii_lowercase();
        if word.is_empty() {
            return None;
        }
        match word.parse::<SupervisorCommand>() {
            Ok(c) => {
                (self.say)(&format!("supervisor: {c}"));
                Some(c)
            }
            Err(_) if word == "done" || word == "failed" => {
                (self.say)(&format!(
                    "supervisor: `{word}` ends an intervention, and none is pending"
                ));
                None
            }
            Err(e) => {
                (self.say)(&format!("supervisor: {e}"));
                None
            }
        }
    }
}

impl Supervisor for ConsoleSupervisor {
    fn next_poll(&self, _at: &Moment) -> Option<NextPoll> {
        Some(NextPoll::Every(LIVE_POLL))
    }

    fn source(&self) -> &str {
        &self.from
    }

    fn refused(&mut self) -> Option<Refusal> {
        self.refusals.as_ref()?.try_recv().ok()
    }

    fn poll(&mut self, _at: &Moment) -> Option<SupervisorCommand> {
        loop {
            match self.lines.try_recv() {
                Ok((line, from)) => {
                    self.from = from;
                    if let Some(c) = self.command(&line) {
                        return Some(c);
                    }
                }
                Err(TryRecvError::Empty) => return None,
                Err(TryRecvError::Disconnected) => {
                    // Nobody can type a command from now on: say so at once, not at the
                    // next wait. The run goes on (Ctrl-C still holds both arms); a wait
                    // for the surgeon aborts it.
                    if !self.closed_said {
                        self.closed_said = true;
                        (self.say)(
                            "supervisor: end of input: no command can be typed from now on; \
                             the run goes on, Ctrl-C holds both arms and ends it, and a \
                             wait for you aborts it",
                        );
                    }
                    return None;
                }
            }
        }
    }

    fn wait(&mut self) -> Option<SupervisorCommand> {
        (self.say)(&format!(
            "supervisor: the arms hold; the run waits for you: type {COMMANDS}"
        ));
        loop {
            let Some(line) = self.next_line() else {
                (self.say)("supervisor: end of input: the run aborts, arms held");
                return None;
            };
            if let Some(c) = self.command(&line) {
                return Some(c);
            }
        }
    }

    fn intervene(&mut self, request: &InterventionRequest) -> InterventionResult {
        (self.say)(&format!(
            "supervisor: the robot asks for help: throw {} step {} ({}) failed, class {}. \
             The arms hold. Take over, ready the workspace for that step, then type `done` \
             (or `failed` if it cannot go on).",
            request.throw + 1,
            request.step + 1,
            request.primitive,
            request.class
        ));
        loop {
            let Some(line) = self.next_line() else {
                (self.say)("supervisor: end of input: the intervention failed");
                return InterventionResult::Failed;
            };
            match line.trim().to_ascii_lowercase().as_str() {
                "done" => return InterventionResult::Recovered,
                "failed" | "abort" | "e-stop" => return InterventionResult::Failed,
                "" => {}
                other => (self.say)(&format!(
                    "supervisor: `{other}`: type `done` when the workspace is ready, or \
                     `failed`"
                )),
            }
        }
    }

    fn checkpoint(&mut self, request: &CheckpointRequest) -> Option<SupervisorCommand> {
        (self.say)(&format!(
            "supervisor: checkpoint before throw {} goes on: \"{}\". The arms hold. Type `go` \
             to confirm, or abort, e-stop, take-over.",
            request.throw + 1,
            request.label
        ));
        loop {
            let Some(line) = self.next_line() else {
                (self.say)("supervisor: end of input: the run aborts, arms held");
                return None;
            };
            match self.command(&line) {
                Some(
                    c @ (SupervisorCommand::Go
                    | SupervisorCommand::Abort
                    | SupervisorCommand::EStop
                    | SupervisorCommand::TakeOver),
                ) => return Some(c),
                Some(other) => (self.say)(&format!(
                    "supervisor: `{other}` does not answer a checkpoint: type go, abort, e-stop \
                     or take-over"
                )),
                None => {}
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::{Arc, Mutex};
    use stitch_engine::FailureClass;

    fn console(lines: &[&str], close: bool) -> (ConsoleSupervisor, Arc<Mutex<Vec<String>>>) {
        let (tx, rx) = std::sync::mpsc::channel();
        for l in lines {
            tx.send(((*l).to_string(), "terminal".to_string()))
                .expect("send");
        }
        if !close {
            // Keep input open: leak the sender for the test's life.
            std::mem::forget(tx);
        }
        let said = Arc::new(Mutex::new(Vec::new()));
        let sink = Arc::clone(&said);
        let say = Box::new(move |s: &str| sink.lock().expect("said").push(s.to_string()));
        (ConsoleSupervisor::new(rx, say), said)
    }

    fn at(attempts: usize) -> Moment {
        use std::time::Duration;
        Moment {
            attempts,
            now: Duration::ZERO,
            mid_step: false,
            committed: false,
        }
    }

    fn request() -> InterventionRequest {
        InterventionRequest {
            throw: 1,
            step: 2,
            primitive: "extract",
            class: FailureClass::Extraction,
        }
    }

    #[test]
    fn typed_commands_arrive_at_the_next_poll_and_bad_ones_are_explained() {
        let (mut s, said) = console(&["", "  Pause ", "melt", "done", "resume"], false);
        assert_eq!(s.poll(&at(0)), Some(SupervisorCommand::Pause));
        assert_eq!(s.poll(&at(1)), Some(SupervisorCommand::Resume));
        assert_eq!(s.poll(&at(2)), None, "nothing more typed");
        let said = said.lock().expect("said").join("\n");
        assert!(said.contains("unknown supervisor command `melt`"), "{said}");
        assert!(said.contains("none is pending"), "{said}");
    }

    #[test]
    fn the_end_of_input_mid_run_is_said_at_once_and_once() {
        let (mut s, said) = console(&["pause"], true);
        assert_eq!(s.poll(&at(0)), Some(SupervisorCommand::Pause));
        assert_eq!(s.poll(&at(1)), None);
        assert_eq!(s.poll(&at(2)), None);
        let said = said.lock().expect("said").clone();
        let ends = said.iter().filter(|l| l.contains("end of input")).count();
        assert_eq!(ends, 1, "{said:?}");
        assert!(
            said.iter().any(|l| l.contains("Ctrl-C holds both arms")),
            "{said:?}"
        );
    }

    #[test]
    fn a_pause_waits_for_the_next_command_and_end_of_input_aborts() {
        let (mut s, _) = console(&["nonsense", "hand-back"], true);
        assert_eq!(s.wait(), Some(SupervisorCommand::HandBack));
        assert_eq!(s.wait(), None, "input closed");
    }

    #[test]
    fn an_intervention_ends_as_the_surgeon_says() {
        let (mut s, said) = console(&["resume", "done"], false);
        assert_eq!(s.intervene(&request()), InterventionResult::Recovered);
        let said = said.lock().expect("said").join("\n");
        assert!(
            said.contains("throw 2 step 3 (extract) failed, class E"),
            "{said}"
        );
        assert!(
            said.contains("type `done` when the workspace is ready"),
            "{said}"
        );
        let (mut s, _) = console(&["failed"], false);
        assert_eq!(s.intervene(&request()), InterventionResult::Failed);
        let (mut s, _) = console(&[], true);
        assert_eq!(s.intervene(&request()), InterventionResult::Failed);
    }

    #[test]
    fn a_checkpoint_waits_for_go_or_a_stop_and_end_of_input_aborts() {
        let request = CheckpointRequest {
            throw: 0,
            step: 0,
            label: "first insertion".into(),
        };
        let (mut s, said) = console(&["resume", "Go"], false);
        assert_eq!(s.checkpoint(&request), Some(SupervisorCommand::Go));
        let said = said.lock().expect("said").join("\n");
        assert!(
            said.contains("\"first insertion\". The arms hold."),
            "{said}"
        );
        assert!(
            said.contains("`resume` does not answer a checkpoint"),
            "{said}"
        );
        let (mut s, _) = console(&["e-stop"], false);
        assert_eq!(s.checkpoint(&request), Some(SupervisorCommand::EStop));
        let (mut s, _) = console(&[], true);
        assert_eq!(s.checkpoint(&request), None, "input closed: the run aborts");
    }

    #[test]
    fn the_web_console_s_words_are_heard_as_typed_ones_and_say_who_sent_them() {
        let (tx, rx) = std::sync::mpsc::channel();
        let (refuse, refusals) = std::sync::mpsc::channel();
        let viewer = "console viewer 2 (127.0.0.1:50412)".to_string();
        tx.send(("done".to_string(), viewer.clone())).expect("send");
        tx.send(("pause".to_string(), viewer.clone()))
            .expect("send");
        std::mem::forget(tx);
        let mut c = ConsoleSupervisor::new(rx, Box::new(|_| {}));
        c.refusals = Some(refusals);
        assert_eq!(c.intervene(&request()), InterventionResult::Recovered);
        assert_eq!(c.source(), viewer);
        assert_eq!(c.poll(&at(0)), Some(SupervisorCommand::Pause));
        refuse
            .send(Refusal {
                command: "pause".into(),
                from: "console 127.0.0.1:1".into(),
                why: "wrong token".into(),
            })
            .expect("send");
        assert_eq!(c.refused().map(|r| r.why), Some("wrong token".to_string()));
        assert_eq!(c.refused(), None);
    }
}
