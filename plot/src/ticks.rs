//! Axis tick positions and labels: "nice" linear steps, decades or powers of two on log axes.

/// Tick positions (in data units) for a linear axis covering `[lo, hi]`: steps of 1, 2 or 5 × 10^k.
pub fn linear_ticks(lo: f64, hi: f64) -> Vec<f64> {
    let span = hi - lo;
    if span.is_nan() || span <= 0.0 {
        return vec![lo];
    }
    let raw = span / 6.0;
    let mag = 10f64.powf(raw.log10().floor());
    let step = [1.0, 2.0, 5.0, 10.0]
        .iter()
        .map(|m| m * mag)
        .find(|s| span / s <= 8.0)
        .unwrap_or(10.0 * mag);
    let first = (lo / step).ceil() as i64;
    let last = (hi / step).floor() as i64;
    (first..=last).map(|k| clean(k as f64 * step)).collect()
}

/// Tick positions (in data units, all > 0) for a log axis covering `[lo, hi]` (`0 < lo < hi`).
///
/// Powers of two when at least 3/4 of the data values are powers of two (codebook sizes:
/// 256, 1024, 4096, with a few fitted optima among them),
/// otherwise decades (every k-th decade when there are many), with 2× and 5× marks when the
/// range spans few decades, and plain linear ticks inside a single decade.
pub fn log_ticks(lo: f64, hi: f64, data: &[f64]) -> Vec<f64> {
    if !(lo > 0.0 && hi > lo) {
        return vec![lo];
    }
    let twos = data.iter().filter(|&&v| is_power_of_two(v)).count();
    let powers_of_two = !data.is_empty() && 4 * twos >= 3 * data.len();
    if powers_of_two {
        let first = lo.log2().ceil() as i32;
        let last = hi.log2().floor() as i32;
        if last > first {
            let count = (last - first + 1) as usize;
            let step = count.div_ceil(9).max(1);
            return (first..=last).step_by(step).map(|e| 2f64.powi(e)).collect();
        }
    }
    let first = lo.log10().ceil() as i32;
    let last = hi.log10().floor() as i32;
    let decades = last - first + 1;
    if decades >= 3 {
        let step = (decades as usize).div_ceil(8).max(1);
        return (first..=last).step_by(step).map(pow10).collect();
    }
    let with_marks: Vec<f64> = (first - 1..=last)
        .flat_map(|e| [1.0, 2.0, 5.0].map(|m| clean(m * pow10(e))))
        .filter(|&v| v >= lo * (1.0 - 1e-12) && v <= hi * (1.0 + 1e-12))
        .collect();
    if with_marks.len() >= 3 {
        return with_marks;
    }
    linear_ticks(lo, hi)
        .into_iter()
        .filter(|&v| v > 0.0)
        .collect()
}

/// 10^e, exact where f64 can hold it (parsed, not multiplied up).
fn pow10(e: i32) -> f64 {
    format!("1e{e}").parse().expect("a valid float literal")
}

/// True when `v` is 2^k for an integer k (to 1e-9 relative).
fn is_power_of_two(v: f64) -> bool {
    v > 0.0 && {
        let e = v.log2();
        (e - e.round()).abs() < 1e-9
    }
}

/// Removes floating-point noise from a product like 3 × 0.1.
fn clean(v: f64) -> f64 {
    if v == 0.0 {
        return 0.0;
    }
    let digits = 12 - v.abs().log10().floor() as i32;
    let scale = 10f64.powi(digits.clamp(-300, 300));
    (v * scale).round() / scale
}

/// A short, readable tick label: `1024`, `0.25`, `10¹⁸`, `3×10⁻⁴`.
pub fn format_tick(v: f64) -> String {
    if v == 0.0 || !v.is_finite() {
        return if v == 0.0 { "0".into() } else { v.to_string() };
    }
    let a = v.abs();
    if (1e-3..1e6).contains(&a) {
        return trim(format!("{:.*}", decimals(a), v));
    }
    let mut exp = a.log10().floor() as i32;
    // The mantissa as shown (two decimals); 9.998 rounds up to the next power.
    let mut mantissa = (v / 10f64.powi(exp) * 100.0).round() / 100.0;
    if mantissa.abs() >= 10.0 {
        mantissa /= 10.0;
        exp += 1;
    }
    let power = format!("10{}", superscript(exp));
    if (mantissa.abs() - 1.0).abs() < 1e-9 {
        if mantissa < 0.0 {
            format!("−{power}")
        } else {
            power
        }
    } else {
        format!("{}×{power}", trim(format!("{mantissa:.2}")))
    }
}

/// Decimals that show up to six significant digits of a number in [1e-3, 1e6).
fn decimals(a: f64) -> usize {
    (5 - a.log10().floor() as i32).clamp(0, 8) as usize
}

/// Drops trailing zeros (and a trailing point) of a fixed-point number.
fn trim(s: String) -> String {
    if s.contains('.') {
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        s
    }
}

/// An integer in Unicode superscript digits (DejaVu Sans has them all).
fn superscript(n: i32) -> String {
    let digits = ['⁰', '¹', '²', '³', '⁴', '⁵', '⁶', '⁷', '⁸', '⁹'];
    let mut out = String::new();
    if n < 0 {
        out.push('⁻');
    }
    for c in n.unsigned_abs().to_string().chars() {
        out.push(digits[c.to_digit(10).expect("decimal digit") as usize]);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn codebook_sizes_get_power_of_two_ticks() {
        let sizes = [256.0, 1024.0, 4096.0, 16384.0, 65536.0];
        let ticks = log_ticks(200.0, 80000.0, &sizes);
        assert_eq!(ticks.first(), Some(&256.0));
        assert_eq!(ticks.last(), Some(&65536.0));
        assert_eq!(ticks.len(), 9, "{ticks:?}");
        let labels: Vec<String> = ticks.iter().map(|&t| format_tick(t)).collect();
        assert!(labels.contains(&"1024".to_string()), "{labels:?}");
        assert!(labels.contains(&"4096".to_string()), "{labels:?}");
        let mixed = [256.0, 1024.0, 4096.0, 700.0];
        assert_eq!(log_ticks(200.0, 5000.0, &mixed).first(), Some(&256.0));
        let measured = [240.0, 1000.0, 4375.0];
        assert_eq!(log_ticks(200.0, 5000.0, &measured).first(), Some(&200.0));
    }

    #[test]
    fn wide_log_range_gets_decades() {
        let ticks = log_ticks(3e17, 2e21, &[1e18, 1e21]);
        assert_eq!(ticks, vec![1e18, 1e19, 1e20, 1e21]);
        assert_eq!(format_tick(1e18), "10¹⁸");
        let many = log_ticks(1.0, 1e20, &[1.0, 3.0]);
        assert!(many.len() <= 9 && many.len() >= 5, "{many:?}");
    }

    #[test]
    fn narrow_log_range_gets_one_two_five() {
        let ticks = log_ticks(0.8, 60.0, &[1.0, 3.0]);
        assert_eq!(ticks, vec![1.0, 2.0, 5.0, 10.0, 20.0, 50.0]);
    }

    #[test]
    fn linear_ticks_are_round() {
        assert_eq!(linear_ticks(0.0, 1.0), vec![0.0, 0.2, 0.4, 0.6, 0.8, 1.0]);
        assert_eq!(linear_ticks(2.13, 2.61), vec![2.2, 2.3, 2.4, 2.5, 2.6]);
    }

    #[test]
    fn labels_are_short() {
        assert_eq!(format_tick(0.25), "0.25");
        assert_eq!(format_tick(2.5), "2.5");
        assert_eq!(format_tick(65536.0), "65536");
        assert_eq!(format_tick(3e-4), "3×10⁻⁴");
        assert_eq!(format_tick(2.5e9), "2.5×10⁹");
        assert_eq!(format_tick(-1e7), "−10⁷");
        assert_eq!(format_tick(9.998e19), "10²⁰");
        assert_eq!(format_tick(6.006e18), "6.01×10¹⁸");
    }
}
