//! Flow recovers known motions of procedural textures.

use cpsl_flow::{flow, FlowConfig, FlowError, FlowMethod, Grey};

/// A smooth, richly textured pattern (sum of sines at several scales and angles).
fn texture(x: f32, y: f32) -> f32 {
    let mut v = 0.5;
    for (i, (fx, fy)) in [(0.11, 0.07), (-0.05, 0.13), (0.23, -0.19), (0.031, 0.047)]
        .iter()
        .enumerate()
    {
        v += 0.12 * ((x * fx + y * fy) * (1.0 + i as f32 * 0.3)).sin();
    }
    v
}

fn image(w: usize, h: usize, f: impl Fn(f32, f32) -> f32) -> Grey {
    Grey {
        width: w,
        height: h,
        data: (0..w * h)
            .map(|p| f((p % w) as f32, (p / w) as f32))
            .collect(),
    }
}

/// Mean endpoint error over pixels at least `margin` from the border where `mask` holds.
fn epe(f: &cpsl_flow::Flow, truth: impl Fn(usize, usize) -> (f32, f32), margin: usize) -> f32 {
    let (mut s, mut n) = (0.0, 0.0);
    for y in margin..f.height - margin {
        for x in margin..f.width - margin {
            let (u, v) = f.at(x, y);
            let (tu, tv) = truth(x, y);
            s += ((u - tu).powi(2) + (v - tv).powi(2)).sqrt();
            n += 1.0;
        }
    }
    s / n
}

#[test]
fn recovers_global_translations_small_and_large() {
    // DIS at the video layering's flow grid (its coarsest level, an eighth of that, sets its
    // reach), Lucas-Kanade also on a smaller image (its pyramid goes down to 8 pixels).
    let cases = [
        (FlowMethod::Dis, (320, 180), 0.15),
        (FlowMethod::LucasKanade, (320, 180), 0.15),
        (FlowMethod::LucasKanade, (160, 120), 0.15),
    ];
    for (method, (w, h), max) in cases {
        let cfg = FlowConfig {
            method,
            ..FlowConfig::default()
        };
        for (u, v) in [
            (0.0f32, 0.0f32),
            (1.3, -0.6),
            (6.5, 3.25),
            (-11.0, 4.0),
            (-20.0, 8.0),
        ] {
            if (w, u) == (160, -20.0) {
                continue;
            }
            let a = image(w, h, texture);
            let b = image(w, h, |x, y| texture(x - u, y - v));
            let f = flow(&a, &b, &cfg).unwrap();
            let e = epe(&f, |_, _| (u, v), 16);
            eprintln!("{method:?} {w}x{h} ({u}, {v}): EPE {e:.3} px");
            assert!(e < max, "{method:?} {w}x{h} ({u}, {v}): EPE {e:.3}");
        }
    }
}

#[test]
fn small_images_take_lucas_kanade() {
    // Under DIS's smallest side the default method gives Lucas-Kanade's flow.
    let (u, v) = (1.5f32, -0.5f32);
    let a = image(40, 12, texture);
    let b = image(40, 12, |x, y| texture(x - u, y - v));
    let lk = FlowConfig {
        method: FlowMethod::LucasKanade,
        ..FlowConfig::default()
    };
    assert_eq!(
        flow(&a, &b, &FlowConfig::default()).unwrap(),
        flow(&a, &b, &lk).unwrap()
    );
}

#[test]
fn separates_a_moving_square_from_a_static_background() {
    let (u, v) = (4.0f32, -2.0f32);
    let square = |x: f32, y: f32| (40.0..90.0).contains(&x) && (30.0..80.0).contains(&y);
    let fg = |x: f32, y: f32| 1.0 - texture(y * 1.7 + 3.0, x * 1.3);
    let a = image(160, 120, |x, y| {
        if square(x, y) {
            fg(x, y)
        } else {
            texture(x, y)
        }
    });
    let b = image(160, 120, |x, y| {
        if square(x - u, y - v) {
            fg(x - u, y - v)
        } else {
            texture(x, y)
        }
    });
    let f = flow(&a, &b, &FlowConfig::default()).unwrap();
    // Away from the square's edges (the window straddles them there).
    let (mut inside, mut outside, mut ni, mut no) = (0.0, 0.0, 0.0, 0.0);
    for y in 8..112 {
        for x in 8..152 {
            let (fx, fy) = f.at(x, y);
            let (xf, yf) = (x as f32, y as f32);
            let deep = (48.0..82.0).contains(&xf) && (38.0..72.0).contains(&yf);
            let far = !(30.0..100.0).contains(&xf) || !(20.0..90.0).contains(&yf);
            if deep {
                inside += ((fx - u).powi(2) + (fy - v).powi(2)).sqrt();
                ni += 1.0;
            } else if far {
                outside += (fx * fx + fy * fy).sqrt();
                no += 1.0;
            }
        }
    }
    let (inside, outside) = (inside / ni, outside / no);
    eprintln!("EPE inside {inside:.3}, outside {outside:.3}");
    assert!(inside < 0.3 && outside < 0.1);
}

#[test]
fn rejects_mismatched_images() {
    let a = image(10, 10, texture);
    let b = image(10, 9, texture);
    assert!(matches!(
        flow(&a, &b, &FlowConfig::default()),
        Err(FlowError::Size { .. })
    ));
    let empty = Grey {
        width: 0,
        height: 0,
        data: vec![],
    };
    assert!(flow(&empty, &empty, &FlowConfig::default()).is_err());
}

#[test]
fn a_scaled_grey_image_is_the_area_mean_of_the_full_one() {
    for (w, h, side) in [(97, 61, 40), (64, 64, 16), (30, 20, 64), (1280, 720, 320)] {
        let rgb: Vec<u8> = (0..w * h * 3).map(|i| ((i * 7919) % 251) as u8).collect();
        let full = Grey::from_rgb8(&rgb, w, h);
        let scaled = Grey::from_rgb8_scaled(&rgb, w, h, side);
        let s = (side as f32 / w.max(h) as f32).min(1.0);
        let (gw, gh) = if s >= 1.0 {
            (w, h)
        } else {
            (
                ((w as f32 * s).round() as usize).max(1),
                ((h as f32 * s).round() as usize).max(1),
            )
        };
        assert_eq!((scaled.width, scaled.height), (gw, gh));
        for y in 0..gh {
            let (y0, y1) = (y * h / gh, ((y + 1) * h / gh).max(y * h / gh + 1));
            for x in 0..gw {
                let (x0, x1) = (x * w / gw, ((x + 1) * w / gw).max(x * w / gw + 1));
                let sum: f32 = (y0..y1)
                    .map(|yy| full.data[yy * w + x0..yy * w + x1].iter().sum::<f32>())
                    .sum();
                let want = sum / ((y1 - y0) * (x1 - x0)) as f32;
                assert_eq!(
                    scaled.data[y * gw + x].to_bits(),
                    want.to_bits(),
                    "{w}x{h} ({x}, {y})"
                );
            }
        }
    }
}
