//! Helpers shared by integration tests.

use std::path::Path;

/// A minimal `.npy` writer (format 1.0, C order): `descr` is the numpy type
/// string (`<f4`, `<f8`), `payload` the little-endian values.
#[allow(dead_code)]
pub fn write_npy(path: &Path, shape: &[usize], descr: &str, payload: &[u8]) {
    let dims: Vec<String> = shape.iter().map(|d| d.to_string()).collect();
    let shape = if dims.len() == 1 {
        format!("({},)", dims[0])
    } else {
        format!("({})", dims.join(", "))
    };
    let mut header = format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}");
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut bytes = b"\x93NUMPY\x01\x00".to_vec();
    bytes.extend((header.len() as u16).to_le_bytes());
    bytes.extend(header.as_bytes());
    bytes.extend(payload);
    std::fs::write(path, bytes).unwrap();
}

/// The demo tabletop at 40³ as a script command (small enough for tests that
/// replay sessions many times).
#[allow(dead_code)]
pub const DEMO_RES: usize = 40;

#[allow(dead_code)]
pub fn load_demo() -> isrf::command::Edit {
    isrf::command::Edit::LoadField {
        name: "tabletop".into(),
        source: isrf::command::FieldSource::Demo {
            scene: "tabletop".into(),
            res: DEMO_RES,
            seed: 0,
        },
        transform: None,
    }
}

/// A stroke from the demo's built-in stroke for `object`.
#[allow(dead_code)]
pub fn demo_stroke(object: &str) -> isrf::command::Edit {
    isrf::command::Edit::Stroke {
        object: object.into(),
        field: None,
        polarity: None,
        source: isrf::command::StrokeSource::Demo { object: object.into() },
    }
}

/// Updates a headless editor app until its session has no queued or running
/// request, then one more frame so entities mirror the final state.
#[cfg(feature = "editor")]
#[allow(dead_code)]
pub fn settle(app: &mut bevy::prelude::App) {
    use isrf::app::editor::session::EditorSession;
    for _ in 0..20_000 {
        app.update();
        if !app.world().resource::<EditorSession>().busy() {
            app.update();
            return;
        }
        std::thread::sleep(std::time::Duration::from_millis(2));
    }
    panic!("the session never finished its requests");
}
