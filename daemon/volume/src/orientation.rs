//! Patient orientation: which anatomical direction each world axis of a volume points to, where
//! the file says so (NRRD `space`, NIfTI qform/sform, DICOM ImageOrientationPatient). World space
//! stays the volume's own grid space (DESIGN.md "Data"); this only names its axes.

use glam::DVec3;

/// A direction of the patient's body.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum PatientDir {
    Left,
    Right,
    Anterior,
    Posterior,
    Superior,
    Inferior,
}

impl PatientDir {
    /// The direction the other way.
    pub fn opposite(self) -> PatientDir {
        use PatientDir::*;
        match self {
            Left => Right,
            Right => Left,
            Anterior => Posterior,
            Posterior => Anterior,
            Superior => Inferior,
            Inferior => Superior,
        }
    }

    /// The one-letter code of the DICOM/NIfTI conventions (L, R, A, P, S, I).
    pub fn letter(self) -> char {
        use PatientDir::*;
        match self {
            Left => 'L',
            Right => 'R',
            Anterior => 'A',
            Posterior => 'P',
            Superior => 'S',
            Inferior => 'I',
        }
    }

    /// The unit vector of this direction in DICOM's patient frame (LPS: +x left, +y posterior,
    /// +z superior).
    pub fn lps(self) -> DVec3 {
        use PatientDir::*;
        match self {
            Left => DVec3::X,
            Right => -DVec3::X,
            Posterior => DVec3::Y,
            Anterior => -DVec3::Y,
            Superior => DVec3::Z,
            Inferior => -DVec3::Z,
        }
    }

    /// 0 for left-right, 1 for anterior-posterior, 2 for superior-inferior.
    fn anatomical_axis(self) -> usize {
        use PatientDir::*;
        match self {
            Left | Right => 0,
            Anterior | Posterior => 1,
            Superior | Inferior => 2,
        }
    }
}

/// The patient frame a file's coordinates are given in: which way its +x, +y, +z point.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PatientFrame {
    /// +x left, +y posterior, +z superior (DICOM, NRRD `left-posterior-superior`).
    Lps,
    /// +x right, +y anterior, +z superior (NIfTI, NRRD `right-anterior-superior`).
    Ras,
}

impl PatientFrame {
    fn axes(self) -> [PatientDir; 3] {
        match self {
            PatientFrame::Lps => [PatientDir::Left, PatientDir::Posterior, PatientDir::Superior],
            PatientFrame::Ras => [PatientDir::Right, PatientDir::Anterior, PatientDir::Superior],
        }
    }

    /// A vector given in this frame, in LPS.
    fn to_lps(self, v: DVec3) -> DVec3 {
        let [x, y, z] = self.axes().map(PatientDir::lps);
        v.x * x + v.y * y + v.z * z
    }
}

/// Where each world axis of a volume points on the patient: `axes[a]` is the direction of +a
/// (a = x, y, z). The three name the three anatomical axes, each once.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Orientation {
    axes: [PatientDir; 3],
}

impl Orientation {
    /// The orientation of a volume without one, for naming views: the world axes taken as LPS
    /// (DICOM's patient frame: +x left, +y posterior, +z superior, world up +z), so the anterior
    /// side is -y.
    pub const ASSUMED: Orientation =
        Orientation { axes: [PatientDir::Left, PatientDir::Posterior, PatientDir::Superior] };

    /// An orientation from the directions of +x, +y, +z; `None` unless they are the three
    /// anatomical axes, each once.
    pub fn new(axes: [PatientDir; 3]) -> Option<Orientation> {
        let mut seen = [false; 3];
        for d in axes {
            seen[d.anatomical_axis()] = true;
        }
        seen.iter().all(|&s| s).then_some(Orientation { axes })
    }

    /// The direction +x, +y, +z point to.
    pub fn axes(&self) -> [PatientDir; 3] {
        self.axes
    }

    /// The three-letter code (e.g. `LPS`, `RAS`).
    pub fn code(&self) -> String {
        self.axes.iter().map(|d| d.letter()).collect()
    }

    /// The world unit vector that points towards `dir` on the patient.
    pub fn world_dir(&self, dir: PatientDir) -> DVec3 {
        let mut v = DVec3::ZERO;
        for (a, &d) in self.axes.iter().enumerate() {
            if d == dir {
                v[a] = 1.0;
            } else if d == dir.opposite() {
                v[a] = -1.0;
            }
        }
        v
    }

    /// The orientation of grid axes whose directions in `frame` are `columns` (each the world
    /// direction of one grid axis, any length): each axis takes the patient direction it leans
    /// towards most. `None` where an axis is zero or not finite, leans equally towards two
    /// anatomical axes (45 degrees off both), or two axes lean towards the same one.
    pub fn from_directions(columns: [DVec3; 3], frame: PatientFrame) -> Option<Orientation> {
        let frame_axes = frame.axes();
        let mut axes = [PatientDir::Left; 3];
        for (a, c) in columns.iter().enumerate() {
            let len = c.length();
            if !c.is_finite() || len == 0.0 || !len.is_finite() {
                return None;
            }
            let u = *c / len;
            let mut order = [0usize, 1, 2];
            order.sort_by(|&p, &q| u[q].abs().total_cmp(&u[p].abs()));
            let (best, second) = (u[order[0]].abs(), u[order[1]].abs());
            if best - second < 1e-6 {
                return None;
            }
            let d = frame_axes[order[0]];
            axes[a] = if u[order[0]] > 0.0 { d } else { d.opposite() };
        }
        Orientation::new(axes)
    }
}

/// The exact directions of a volume's world axes on the patient, as LPS unit vectors: what the
/// file said, an oblique grid's included, where [`Orientation`] keeps only the nearest patient
/// axis of each. A writer puts the grid back where the file had it from these (DICOM's
/// ImageOrientationPatient); views are still named by the [`Orientation`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PatientAxes {
    lps: [DVec3; 3],
}

impl PatientAxes {
    /// The axes whose directions in `frame` are `columns` (each the world direction of one grid
    /// axis, any length). `None` where one is zero or not finite, or two are not orthogonal (a
    /// cosine above 1e-3): a sheared grid has no patient axes.
    pub fn new(columns: [DVec3; 3], frame: PatientFrame) -> Option<PatientAxes> {
        let mut lps = [DVec3::ZERO; 3];
        for (a, c) in columns.iter().enumerate() {
            let len = c.length();
            if !c.is_finite() || len == 0.0 || !len.is_finite() {
                return None;
            }
            lps[a] = frame.to_lps(*c / len);
        }
        let orthogonal = [(0, 1), (0, 2), (1, 2)].iter().all(|&(p, q)| lps[p].dot(lps[q]).abs() <= 1e-3);
        orthogonal.then_some(PatientAxes { lps })
    }

    /// The axes of an orientation, each exactly along its patient direction.
    pub fn of(orientation: Orientation) -> PatientAxes {
        PatientAxes { lps: orientation.axes.map(PatientDir::lps) }
    }

    /// The LPS unit vectors of +x, +y, +z.
    pub fn lps(&self) -> [DVec3; 3] {
        self.lps
    }

    /// Whether +x, +y, +z make a right-handed frame on the patient (a mirrored grid does not).
    pub fn right_handed(&self) -> bool {
        self.lps[0].cross(self.lps[1]).dot(self.lps[2]) > 0.0
    }

    /// The nearest patient direction of each axis ([`Orientation::from_directions`]).
    pub fn orientation(&self) -> Option<Orientation> {
        Orientation::from_directions(self.lps, PatientFrame::Lps)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use PatientDir::*;

    #[test]
    fn world_directions_follow_the_axes_and_their_opposites() {
        let o = Orientation::new([Right, Inferior, Posterior]).unwrap();
        assert_eq!(o.world_dir(Right), DVec3::X);
        assert_eq!(o.world_dir(Left), -DVec3::X);
        assert_eq!(o.world_dir(Superior), -DVec3::Y);
        assert_eq!(o.world_dir(Anterior), -DVec3::Z);
        assert_eq!(o.code(), "RIP");
        assert_eq!(Orientation::ASSUMED.world_dir(Anterior), -DVec3::Y);
        assert!(Orientation::new([Left, Right, Superior]).is_none(), "left-right twice");
    }

    #[test]
    fn directions_take_the_nearest_patient_axis_or_none() {
        // An axial DICOM grid, slightly tilted: rows left, columns posterior, slices superior.
        let tilt = [DVec3::new(1.0, 0.05, 0.0), DVec3::new(-0.05, 1.0, 0.0), DVec3::Z];
        assert_eq!(Orientation::from_directions(tilt, PatientFrame::Lps).unwrap().code(), "LPS");
        // The same columns in RAS, one flipped: x right, y anterior, z inferior.
        let flipped = [DVec3::X, DVec3::Y, -2.5 * DVec3::Z];
        assert_eq!(Orientation::from_directions(flipped, PatientFrame::Ras).unwrap().code(), "RAI");
        // A sagittal grid: x posterior, y inferior, z right (RAS file frame).
        let sagittal = [-DVec3::Y, -DVec3::Z, DVec3::X];
        assert_eq!(Orientation::from_directions(sagittal, PatientFrame::Ras).unwrap().code(), "PIR");
        let diagonal = [DVec3::new(1.0, 1.0, 0.0), DVec3::new(-1.0, 1.0, 0.0), DVec3::Z];
        assert!(Orientation::from_directions(diagonal, PatientFrame::Lps).is_none());
        let twice = [DVec3::X, DVec3::new(1.0, 0.2, 0.0), DVec3::Z];
        assert!(Orientation::from_directions(twice, PatientFrame::Lps).is_none());
        for bad in [DVec3::ZERO, DVec3::NAN, DVec3::new(f64::INFINITY, 0.0, 0.0)] {
            assert!(Orientation::from_directions([bad, DVec3::Y, DVec3::Z], PatientFrame::Lps).is_none());
        }
    }

    #[test]
    fn patient_axes_are_the_files_directions_in_lps() {
        // RAS's axes are LPS's first two turned over.
        let ras = PatientAxes::new([DVec3::X, 2.0 * DVec3::Y, DVec3::Z], PatientFrame::Ras).unwrap();
        assert_eq!(ras.lps(), [-DVec3::X, -DVec3::Y, DVec3::Z]);
        assert_eq!(ras, PatientAxes::of(Orientation::new([Right, Anterior, Superior]).unwrap()));
        assert_eq!(ras.orientation().unwrap().code(), "RAS");
        assert!(ras.right_handed());
        // An oblique sagittal grid keeps its exact directions, and is named by the nearest axes.
        let oblique = [DVec3::new(0.0, 0.8, 0.6), DVec3::new(0.0, -0.6, 0.8), DVec3::X];
        let axes = PatientAxes::new(oblique, PatientFrame::Lps).unwrap();
        assert_eq!(axes.lps(), oblique);
        assert_eq!(axes.orientation().unwrap().code(), "PSL");
        // A mirrored grid is left-handed; a sheared one has no axes.
        let mirrored = PatientAxes::of(Orientation::new([Left, Posterior, Inferior]).unwrap());
        assert!(!mirrored.right_handed());
        assert!(
            PatientAxes::new([DVec3::X, DVec3::new(0.1, 1.0, 0.0), DVec3::Z], PatientFrame::Lps).is_none()
        );
        assert!(PatientAxes::new([DVec3::ZERO, DVec3::Y, DVec3::Z], PatientFrame::Lps).is_none());
    }
}
