//! `isowall session CONFIG`: drive the wall from the terminal keyboard and a gamepad. Input is
//! read on two threads of its own (crossterm in raw mode; gilrs polling), which send to the frame
//! loop through a channel: input never blocks a frame. The loop applies what arrived (the logic
//! is in `controls.rs`), renders a frame, and redraws a status line (fps, the slowest node, swap
//! skew, iso, AO samples, IBL). While nothing changes the wall keeps refining its progressive AO.

use crate::controls::{action_for_key, Action, Axes, Key, SessionState, KEY_HELP};
use crate::drive::{load, runtime, scene_range_and_framing, time_steps};
use crate::picture::compose;
use crate::start::{self, StartArgs};
use crate::wall::FrameRequest;
use anyhow::{Context, Result};
use clap::Args;
use isowall_model::joystick::{JoystickConfig, PadAxis, PadButton};
use std::io::IsTerminal;
use std::io::Write;
use std::path::PathBuf;
use std::sync::mpsc;
use std::time::{Duration, Instant};

#[derive(Args)]
pub struct SessionArgs {
    /// The wall config (TOML); its [joystick] table maps the gamepad
    pub config: PathBuf,
    /// Folder for screenshots (whole-wall PNGs, `p` or the gamepad's screenshot button)
    #[arg(long, value_name = "DIR", default_value = ".")]
    pub screenshots: PathBuf,
    /// No gamepad (keyboard only)
    #[arg(long)]
    pub no_joystick: bool,
    #[command(flatten)]
    pub start: StartArgs,
}

/// What the input threads send.
enum Input {
    Action(Action),
    Axes(Axes),
    /// An input source gave up (said once, on the status line's next redraw).
    Note(String),
}

/// Restores the terminal when dropped (also on errors and panics unwinding through the session).
struct RawMode;

impl Drop for RawMode {
    fn drop(&mut self) {
        let _ = crossterm::terminal::disable_raw_mode();
    }
}

fn keyboard(tx: mpsc::Sender<Input>) {
    use crossterm::event::{self, Event, KeyCode, KeyEventKind, KeyModifiers};
    loop {
        let ev = match event::read() {
            Ok(ev) => ev,
            Err(e) => {
                let _ = tx.send(Input::Note(format!("keyboard: {e}")));
                return;
            }
        };
        let Event::Key(k) = ev else { continue };
        if k.kind == KeyEventKind::Release {
            continue;
        }
        let key = match k.code {
            KeyCode::Char('c') if k.modifiers.contains(KeyModifiers::CONTROL) => Key::CtrlC,
            KeyCode::Char(c) => Key::Char(c),
            KeyCode::Left => Key::Left,
            KeyCode::Right => Key::Right,
            KeyCode::Up => Key::Up,
            KeyCode::Down => Key::Down,
            KeyCode::PageUp => Key::PageUp,
            KeyCode::PageDown => Key::PageDown,
            KeyCode::Esc => Key::Esc,
            _ => continue,
        };
        if let Some(a) = action_for_key(key) {
            if tx.send(Input::Action(a)).is_err() {
                return;
            }
        }
    }
}

fn gilrs_axis(a: PadAxis) -> gilrs::Axis {
    use gilrs::Axis;
    match a {
        PadAxis::LeftStickX => Axis::LeftStickX,
        PadAxis::LeftStickY => Axis::LeftStickY,
        PadAxis::RightStickX => Axis::RightStickX,
        PadAxis::RightStickY => Axis::RightStickY,
        PadAxis::LeftZ => Axis::LeftZ,
        PadAxis::RightZ => Axis::RightZ,
        PadAxis::DpadX => Axis::DPadX,
        PadAxis::DpadY => Axis::DPadY,
    }
}

fn gilrs_button(b: PadButton) -> gilrs::Button {
    use gilrs::Button;
    match b {
        PadButton::South => Button::South,
        PadButton::East => Button::East,
        PadButton::North => Button::North,
        PadButton::West => Button::West,
        PadButton::LeftTrigger => Button::LeftTrigger,
        PadButton::LeftTrigger2 => Button::LeftTrigger2,
        PadButton::RightTrigger => Button::RightTrigger,
        PadButton::RightTrigger2 => Button::RightTrigger2,
        PadButton::Select => Button::Select,
        PadButton::Start => Button::Start,
        PadButton::Mode => Button::Mode,
        PadButton::LeftThumb => Button::LeftThumb,
        PadButton::RightThumb => Button::RightThumb,
        PadButton::DpadUp => Button::DPadUp,
        PadButton::DpadDown => Button::DPadDown,
        PadButton::DpadLeft => Button::DPadLeft,
        PadButton::DpadRight => Button::DPadRight,
    }
}

fn gamepad(tx: mpsc::Sender<Input>, j: JoystickConfig) {
    let mut gilrs = match gilrs::Gilrs::new() {
        Ok(g) => g,
        Err(e) => {
            let _ = tx.send(Input::Note(format!("no gamepad input: {e}")));
            return;
        }
    };
    let (ax, ay, az) = (gilrs_axis(j.orbit_x), gilrs_axis(j.orbit_y), gilrs_axis(j.zoom));
    let buttons = [
        (gilrs_button(j.iso_up), Action::Iso(1)),
        (gilrs_button(j.iso_down), Action::Iso(-1)),
        (gilrs_button(j.screenshot), Action::Screenshot),
    ];
    let mut axes = Axes::default();
    loop {
        while let Some(gilrs::Event { event, .. }) = gilrs.next_event() {
            let sent = match event {
                gilrs::EventType::ButtonPressed(b, _) => match buttons.iter().find(|(x, _)| *x == b) {
                    Some((_, a)) => tx.send(Input::Action(*a)),
                    None => Ok(()),
                },
                gilrs::EventType::AxisChanged(a, v, _) => {
                    let v = v as f64;
                    if a == ax {
                        axes.orbit_x = v;
                    } else if a == ay {
                        axes.orbit_y = v;
                    } else if a == az {
                        axes.zoom = v;
                    }
                    tx.send(Input::Axes(axes))
                }
                gilrs::EventType::Disconnected => {
                    axes = Axes::default();
                    tx.send(Input::Axes(axes))
                }
                _ => Ok(()),
            };
            if sent.is_err() {
                return;
            }
        }
        std::thread::sleep(Duration::from_millis(8));
    }
}

pub fn session(a: &SessionArgs) -> Result<()> {
    let config = load(&a.config)?;
    let (camera, settings, range, framing) = scene_range_and_framing(&config)?;
    let joystick = config.joystick.clone();
    let mut state = SessionState::new(camera, settings, range);
    state.framing = Some(framing);
    state.playback.steps = time_steps(&config)?;
    std::fs::create_dir_all(&a.screenshots)
        .with_context(|| format!("cannot create {}", a.screenshots.display()))?;
    let (tx, rx) = mpsc::channel::<Input>();
    runtime()?.block_on(async {
        let (daemons, mut wall) = start::open(config, &a.start).await?;
        wall.sync_clocks(5).await;
        let raw = match crossterm::terminal::enable_raw_mode() {
            Ok(()) => {
                let tx = tx.clone();
                std::thread::Builder::new().name("keyboard".into()).spawn(move || keyboard(tx))?;
                Some(RawMode)
            }
            Err(e) => {
                eprintln!("isowall session: no terminal keyboard ({e}); gamepad only, Ctrl-C to stop");
                None
            }
        };
        if !a.no_joystick {
            let tx = tx.clone();
            std::thread::Builder::new()
                .name("gamepad".into())
                .spawn(move || gamepad(tx, joystick.clone()))?;
        }
        drop(tx);
        // On a terminal the status is one line redrawn in place; into a pipe or a file, a plain
        // line a second (no carriage returns or terminal codes in a log).
        let tty = std::io::stdout().is_terminal();
        let mut last_line: Option<Instant> = None;
        print!("isowall session: {KEY_HELP}{}", if tty { "\r\n" } else { "\n" });
        let mut axes = Axes::default();
        let mut note = String::new();
        let mut shots = 0u32;
        let mut last = Instant::now();
        let mut times: std::collections::VecDeque<Instant> = Default::default();
        // Ctrl-C ends this command cleanly (its local nodes stop when it drops them).
        crate::local::interrupt_handled_by_command();
        let ctrl_c = tokio::signal::ctrl_c();
        tokio::pin!(ctrl_c);
        'frames: loop {
            // Everything that arrived since the last frame; never waits.
            let mut screenshot = false;
            while let Ok(input) = rx.try_recv() {
                match input {
                    Input::Action(Action::Screenshot) => screenshot = true,
                    Input::Action(act) => {
                        if state.apply(act) {
                            break 'frames;
                        }
                    }
                    Input::Axes(x) => axes = x,
                    Input::Note(n) => note = n,
                }
            }
            let dt = last.elapsed().as_secs_f64().min(0.25);
            last = Instant::now();
            state.apply_axes(axes, dt, &wall.config.joystick);
            state.playback.advance(dt);
            let request = FrameRequest::new(state.camera, state.settings).at_time_step(state.playback.step);
            tokio::select! {
                r = wall.frame(&request) => r?,
                _ = &mut ctrl_c => break 'frames,
            }
            if screenshot {
                let tiles = wall.snapshot().await;
                let (w, h, rgb) = compose(&wall.config, &tiles);
                shots += 1;
                let out = a.screenshots.join(format!("isowall-session-{shots:03}.png"));
                image::save_buffer(&out, &rgb, w, h, image::ExtendedColorType::Rgb8)
                    .with_context(|| format!("cannot write {}", out.display()))?;
                note = format!("wrote {}", out.display());
            }
            let now = Instant::now();
            times.push_back(now);
            while times.front().is_some_and(|t| now.duration_since(*t) > Duration::from_secs(2)) {
                times.pop_front();
            }
            let fps = if times.len() > 1 {
                (times.len() - 1) as f64 / now.duration_since(times[0]).as_secs_f64().max(1e-9)
            } else {
                0.0
            };
            let (slowest, skew) = match wall.finished.last() {
                Some(f) => (
                    f.per_node
                        .iter()
                        .filter_map(|n| n.render.map(|r| (n.node.clone(), r)))
                        .max_by_key(|x| x.1)
                        .map_or("-".into(), |(n, r)| format!("{n} {:.0} ms", r.as_secs_f64() * 1e3)),
                    f.swap_skew.map_or("-".into(), |s| {
                        let late = if f.late_swaps > 0 {
                            format!(" ({} late)", f.late_swaps)
                        } else {
                            String::new()
                        };
                        format!("{:.2} ms{late}", s.as_secs_f64() * 1e3)
                    }),
                ),
                None => ("-".into(), "-".into()),
            };
            let s = &state.settings;
            let p = &state.playback;
            let step = if p.steps > 1 {
                let late = match wall.finished.last() {
                    Some(f) if f.per_node.iter().any(|n| n.step_late.is_some()) => " (a node waited for it)",
                    _ => "",
                };
                let mode = if p.playing { format!("playing {} steps/s", p.rate) } else { "paused".into() };
                format!(" | step {}/{} {mode}{late}", p.step, p.steps)
            } else {
                String::new()
            };
            let line = format!(
                "{fps:.1} fps | slowest {slowest} | skew {skew} | iso {:.4} | AO {} | IBL {:?}{step} {note}",
                s.iso, s.ao.samples, s.ao.ibl
            );
            if tty {
                print!("\r\x1b[2K{line}");
            } else if last_line.is_none_or(|t| now.duration_since(t) >= Duration::from_secs(1)) {
                println!("{}", line.trim_end());
                last_line = Some(now);
            }
            let _ = std::io::stdout().flush();
        }
        drop(raw);
        if tty {
            print!("\r\n");
        }
        wall.close("the session is over").await;
        drop(daemons);
        Ok(())
    })
}
