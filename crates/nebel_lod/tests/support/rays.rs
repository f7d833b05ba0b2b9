//! Compositing along a ray in a batch's drawn order against the order of
//! the cells' distance along it: the image cost of an order made for
//! another eye.

use nebel_core::cell::{Ray, Tetrahedron};

/// The colour `ray` gets from `cells` composited back to front in their
/// drawn order, and in the order of their distance along the ray: each cell
/// emits its mean scalar `s` and has extinction `extinction · s` per unit
/// length.
pub fn composites(cells: &[Tetrahedron], ray: &Ray, extinction: f64) -> (f64, f64) {
    let mut hits: Vec<(f64, usize, f64, f64)> = cells
        .iter()
        .enumerate()
        .filter_map(|(index, cell)| {
            let segment = cell.intersect(ray)?;
            let entry = segment.t_entry.max(0.0);
            let length = segment.t_exit - entry;
            let scalar = cell.scalars.iter().sum::<f64>() / 4.0;
            let alpha = 1.0 - (-extinction * scalar * length.max(0.0)).exp();
            (length > 1e-4).then_some((entry, index, scalar, alpha))
        })
        .collect();
    let over = |hits: &[(f64, usize, f64, f64)]| {
        hits.iter().fold(0.0, |colour, (_, _, scalar, alpha)| {
            scalar * alpha + (1.0 - alpha) * colour
        })
    };
    hits.sort_by_key(|hit| hit.1);
    let drawn = over(&hits);
    hits.sort_by(|a, b| b.0.total_cmp(&a.0));
    (drawn, over(&hits))
}

/// How far rays composited in a drawn order are from their ray order, over
/// many rays: how many differ, the RMS and the largest difference.
#[derive(Default)]
pub struct OrderCost {
    rays: u32,
    wrong: u32,
    squares: f64,
    worst: f64,
}

impl OrderCost {
    /// Adds one ray's colour in the drawn order and in the ray order.
    pub fn add(&mut self, (drawn, exact): (f64, f64)) {
        let error = (drawn - exact).abs();
        self.rays += 1;
        self.wrong += u32::from(error > 1e-9);
        self.squares += error * error;
        self.worst = self.worst.max(error);
    }

    /// The root mean square of the differences.
    pub fn rmse(&self) -> f64 {
        (self.squares / f64::from(self.rays.max(1))).sqrt()
    }
}

impl std::fmt::Display for OrderCost {
    fn fmt(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        write!(
            f,
            "{} of {} rays differ; RMSE {:.2e}, max {:.2e}",
            self.wrong,
            self.rays,
            self.rmse(),
            self.worst
        )
    }
}
