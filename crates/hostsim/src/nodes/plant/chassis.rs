//! The chassis: a planar rigid body on four mecanum wheels, with friction-limited slip.
//!
//! [`Chassis`] is built from [`ChassisParams`] (e.g. [`ChassisParams::from_config`]) and
//! advanced by [`Chassis::step`] with one [`WheelInput`] per wheel (a drive torque, or a
//! wheel held at a speed); its state is a [`ChassisState`] (world pose, body velocity, wheel
//! speeds). The contact is anisotropic Coulomb friction on the rollers, each step is linearly
//! implicit (unconditionally stable, 1 ms by default), and [`Ripple`] optionally adds the
//! contact-point ripple of Gfrerrer 2008.
//!
//! The model (contact slip and force, equations of motion), the integration, why strafing is
//! slower than driving forward and the ripple are specified in `docs/simulator.md`, section
//! "Chassis".

use kinematics::{ChassisVelocity, MecanumKinematics, Pose2, Twist2, WheelGeometry, wrap_angle};

use super::WHEELS;
use super::error::{ParamError, finite, non_negative, positive};

/// Standard gravity, m/s².
pub const STANDARD_GRAVITY: f64 = 9.806_65;

/// Contact-point ripple after Gfrerrer 2008, eq. 10-11 (see `docs/simulator.md`, section
/// "Chassis", "Contact-point ripple").
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ripple {
    /// Number of rollers `k` per wheel (≥ 3; 8-12 is common).
    pub rollers: u32,
    /// Distance `d` between the wheel axis and a roller axis, m (`0 ≤ d < r`; the roller's
    /// equator radius is `r − d`).
    pub axis_offset: f64,
    /// Per wheel, the wheel angle (rad) at which a roller is centred under the axle.
    pub phase: [f64; WHEELS],
}

impl Ripple {
    /// `rollers` rollers at axis distance `axis_offset` m, all wheels in phase.
    #[must_use]
    pub const fn new(rollers: u32, axis_offset: f64) -> Self {
        Self {
            rollers,
            axis_offset,
            phase: [0.0; WHEELS],
        }
    }

    /// The roller pitch `2π/k`, rad.
    #[must_use]
    pub fn pitch(&self) -> f64 {
        core::f64::consts::TAU / f64::from(self.rollers.max(1))
    }

    /// The wheel angle `u` of eq. 10-11: `wheel_angle − phase` wrapped to `[−π/k, π/k)`.
    #[must_use]
    pub fn local_angle(&self, wheel: usize, wheel_angle: f64) -> f64 {
        let pitch = self.pitch();
        let phase = self.phase.get(wheel).copied().unwrap_or(0.0);
        let u = (wheel_angle - phase).rem_euclid(pitch);
        if u >= 0.5 * pitch { u - pitch } else { u }
    }
}

/// Chassis parameters. [`ChassisParams::default`] is a ~20 kg RoboMaster-like chassis with
/// the geometry of `firmware::Config::dji_m3508_example()`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ChassisParams {
    /// Mass, kg.
    pub mass: f64,
    /// Yaw inertia about the body origin, kg·m².
    pub yaw_inertia: f64,
    /// Wheel geometry, FL, FR, RL, RR (checked for rank 3 by the kinematics crate).
    pub wheels: [WheelGeometry<f64>; WHEELS],
    /// Spin inertia of each wheel as seen at the wheel, kg·m². A [`Plant`](super::Plant)
    /// adds its drive's reflected rotor inertia (`J_rotor · gear²`) to this.
    pub wheel_inertia: [f64; WHEELS],
    /// Normal load per wheel, N; `None` for `m g / 4` each.
    pub normal_load: Option<[f64; WHEELS]>,
    /// Gravity, m/s² (used for the default normal load).
    pub gravity: f64,
    /// Friction coefficient `μ` of the roller on the ground.
    pub friction: f64,
    /// Slip velocity `s0` of the slip curve, m/s: the force reaches `μN/√2` at this slip.
    pub slip_velocity: f64,
    /// Roller drag `ε`: resistance to rolling a roller along its free direction relative to
    /// sliding along its axis (0 = ideal free rollers). Pure strafe settles at
    /// `(1 − ε)/(1 + ε)` of the commanded speed.
    pub roller_drag: f64,
    /// Contact-point ripple (Gfrerrer 2008, eq. 11); `None` (default) for the contact under the
    /// wheel centre.
    pub ripple: Option<Ripple>,
    /// Largest integration step, s (1 ms by default; the implicit contact is stable at any
    /// step, a shorter one resolves faster transients).
    pub max_substep: f64,
}

impl Default for ChassisParams {
    fn default() -> Self {
        Self::standard(0.20, 0.18, 0.076)
    }
}

impl ChassisParams {
    /// Default parameters on a standard layout: wheels at `(±lx, ±ly)`, radius `r`, 45°
    /// rollers pointing to the centre seen from above (the kinematics crate's
    /// `MecanumKinematics::standard`). A layout the kinematics crate refuses (non-finite,
    /// `r <= 0`, singular) gives the defaults' geometry with those numbers anyway and fails
    /// at [`Chassis::new`].
    #[must_use]
    pub fn standard(lx: f64, ly: f64, r: f64) -> Self {
        let q = core::f64::consts::FRAC_PI_4;
        let axle = core::f64::consts::FRAC_PI_2;
        let wheels = [
            WheelGeometry::new(lx, ly, axle, q, r),
            WheelGeometry::new(lx, -ly, axle, -q, r),
            WheelGeometry::new(-lx, ly, axle, -q, r),
            WheelGeometry::new(-lx, -ly, axle, q, r),
        ];
        Self {
            mass: 20.0,
            // A 0.50 m x 0.45 m box of 20 kg: m (a² + b²) / 12.
            yaw_inertia: 0.75,
            wheels,
            // A 152 mm mecanum wheel of ~0.6 kg, hub and rollers: ~0.6 · 0.5 · r² · 1.2.
            wheel_inertia: [2.0e-3; WHEELS],
            normal_load: None,
            gravity: STANDARD_GRAVITY,
            friction: 0.8,
            slip_velocity: 0.05,
            roller_drag: 1.0 / 7.0,
            ripple: None,
            max_substep: 1e-3,
        }
    }

    /// Default parameters on the geometry of a firmware configuration (converted to `f64`).
    /// Mass, inertias and contact stay the defaults; set them for another robot.
    #[must_use]
    pub fn from_config(config: &firmware::Config) -> Self {
        use firmware::config::Geometry;
        match config.geometry {
            // The effectiveness factors are the firmware's estimate of the slip, not the
            // plant's physics: the plant's slip comes from its contact model.
            Geometry::Standard {
                lx,
                ly,
                wheel_radius,
                ..
            } => Self::standard(f64::from(lx), f64::from(ly), f64::from(wheel_radius)),
            Geometry::General { wheels, .. } => Self {
                wheels: wheels.map(|w| {
                    WheelGeometry::new(
                        f64::from(w.x),
                        f64::from(w.y),
                        f64::from(w.axle_angle),
                        f64::from(w.roller_angle),
                        f64::from(w.radius),
                    )
                }),
                ..Self::default()
            },
        }
    }

    /// The same parameters with ideal rollers (`roller_drag = 0`).
    #[must_use]
    pub const fn with_free_rollers(mut self) -> Self {
        self.roller_drag = 0.0;
        self
    }

    /// Normal load of each wheel, N.
    #[must_use]
    pub fn normal_loads(&self) -> [f64; WHEELS] {
        self.normal_load
            .unwrap_or([self.mass * self.gravity / WHEELS as f64; WHEELS])
    }

    /// The kinematics of this layout.
    ///
    /// # Errors
    /// [`ParamError`] naming the geometry field the kinematics crate refused.
    pub fn kinematics(&self) -> Result<MecanumKinematics<f64, WHEELS>, ParamError> {
        MecanumKinematics::new(self.wheels).map_err(|e| {
            use kinematics::GeometryError as G;
            match e {
                G::NonFinite { wheel, field } => {
                    let w = self.wheels.get(wheel).copied();
                    let v = w.map_or(f64::NAN, |w| match field {
                        "x" => w.x,
                        "y" => w.y,
                        "axle_angle" => w.axle_angle,
                        "roller_angle" => w.roller_angle,
                        _ => w.radius,
                    });
                    ParamError::new("chassis.wheels", v, "finite geometry").at(wheel)
                }
                G::NonPositiveRadius { wheel, radius } => {
                    ParamError::new("chassis.wheels.radius", radius, "a radius > 0").at(wheel)
                }
                G::RollerParallelToAxle {
                    wheel,
                    roller_angle,
                } => ParamError::new(
                    "chassis.wheels.roller_angle",
                    roller_angle,
                    "a roller not parallel to its axle",
                )
                .at(wheel),
                G::Singular { condition } => ParamError::new(
                    "chassis.wheels",
                    condition,
                    "a layout of rank 3 (roller axes neither concurrent nor parallel); \
                     value is the condition number",
                ),
                _ => ParamError::new("chassis.wheels", f64::NAN, "a valid layout"),
            }
        })
    }

    /// Checks every field.
    ///
    /// # Errors
    /// [`ParamError`] for the first field out of range.
    pub fn validate(&self) -> Result<(), ParamError> {
        positive("chassis.mass", self.mass)?;
        positive("chassis.yaw_inertia", self.yaw_inertia)?;
        positive("chassis.gravity", self.gravity)?;
        positive("chassis.friction", self.friction)?;
        positive("chassis.slip_velocity", self.slip_velocity)?;
        non_negative("chassis.roller_drag", self.roller_drag)?;
        positive("chassis.max_substep", self.max_substep)?;
        if self.max_substep > 0.01 {
            return Err(ParamError::new(
                "chassis.max_substep",
                self.max_substep,
                "at most 0.01 s",
            ));
        }
        for (i, &j) in self.wheel_inertia.iter().enumerate() {
            positive("chassis.wheel_inertia", j).map_err(|e| e.at(i))?;
        }
        if let Some(loads) = self.normal_load {
            for (i, &n) in loads.iter().enumerate() {
                positive("chassis.normal_load", n).map_err(|e| e.at(i))?;
            }
        }
        self.kinematics()?;
        if let Some(ripple) = &self.ripple {
            if ripple.rollers < 3 {
                return Err(ParamError::new(
                    "chassis.ripple.rollers",
                    f64::from(ripple.rollers),
                    "at least 3 rollers",
                ));
            }
            non_negative("chassis.ripple.axis_offset", ripple.axis_offset)?;
            for (i, w) in self.wheels.iter().enumerate() {
                if ripple.axis_offset >= w.radius {
                    return Err(ParamError::new(
                        "chassis.ripple.axis_offset",
                        ripple.axis_offset,
                        "less than the wheel radius",
                    )
                    .at(i));
                }
                finite("chassis.ripple.phase", ripple.phase[i]).map_err(|e| e.at(i))?;
            }
        }
        Ok(())
    }
}

/// What drives a wheel during a step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum WheelInput {
    /// A drive torque on the wheel, N·m, positive in the wheel's positive (forward) sense.
    Torque(f64),
    /// The wheel is held at this speed, rad/s (an ideal, infinitely stiff servo). The ground
    /// reaction still acts on the chassis; the torque the servo needed is in
    /// [`Contact::load_torque`].
    Speed(f64),
}

/// The chassis state: ground truth.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ChassisState {
    /// World pose; the heading is wrapped to `[−π, π]`.
    pub pose: Pose2<f64>,
    /// Heading, rad, not wrapped (total yaw since the start).
    pub yaw: f64,
    /// Body-frame velocity (m/s, m/s, rad/s).
    pub velocity: ChassisVelocity<f64>,
    /// Wheel speeds, rad/s, FL, FR, RL, RR (positive rolls forward).
    pub wheel_speed: [f64; WHEELS],
    /// Wheel angles, rad, not wrapped.
    pub wheel_angle: [f64; WHEELS],
}

/// One wheel's contact during the last substep (body frame).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Contact {
    /// Contact point `c_i`, m.
    pub position: [f64; 2],
    /// Force of the ground on the chassis, N.
    pub force: [f64; 2],
    /// Axial slip `s_a` (along the roller axis), m/s.
    pub slip_axial: f64,
    /// Roller spin speed `s_f` (along the free direction), m/s.
    pub slip_free: f64,
    /// Ground reaction torque on the wheel `r (F·d)`, N·m: the torque a drive must supply
    /// to hold the wheel's speed.
    pub load_torque: f64,
}

/// Per-wheel constants, precomputed.
#[derive(Debug, Clone, Copy, PartialEq)]
struct WheelConst {
    ax: f64,
    ay: f64,
    /// Rolling direction d.
    dx: f64,
    dy: f64,
    /// Nominal roller axis e_a.
    eax: f64,
    eay: f64,
    /// Axle direction (cos α, sin α) and sin/cos of α, δ (for the ripple).
    cos_a: f64,
    sin_a: f64,
    cos_d: f64,
    sin_d: f64,
    cot_d: f64,
    r: f64,
    mu_n: f64,
    /// Spin inertia of the wheel, kg·m².
    j: f64,
}

/// A planar rigid body on four mecanum wheels (the model: `docs/simulator.md`, section
/// "Chassis").
#[derive(Debug, Clone, PartialEq)]
pub struct Chassis {
    params: ChassisParams,
    consts: [WheelConst; WHEELS],
    substep: f64,
    state: ChassisState,
    contacts: [Contact; WHEELS],
    /// `∫(vx, vy, wz) dt` since the chassis was built: see [`Self::body_travel`].
    travel: [f64; 3],
}

impl Chassis {
    /// A chassis at rest at the origin.
    ///
    /// # Errors
    /// [`ParamError`] for the first parameter out of range.
    pub fn new(params: ChassisParams) -> Result<Self, ParamError> {
        params.validate()?;
        let loads = params.normal_loads();
        let consts = core::array::from_fn(|i| {
            let w = params.wheels[i];
            let (sin_a, cos_a) = libm::sincos(w.axle_angle);
            let (sin_d, cos_d) = libm::sincos(w.roller_angle);
            let (sin_ad, cos_ad) = libm::sincos(w.axle_angle + w.roller_angle);
            WheelConst {
                ax: w.x,
                ay: w.y,
                dx: sin_a,
                dy: -cos_a,
                eax: cos_ad,
                eay: sin_ad,
                cos_a,
                sin_a,
                cos_d,
                sin_d,
                cot_d: cos_d / sin_d,
                r: w.radius,
                mu_n: params.friction * loads[i],
                j: params.wheel_inertia[i],
            }
        });
        Ok(Self {
            params,
            consts,
            substep: params.max_substep,
            state: ChassisState::default(),
            contacts: [Contact::default(); WHEELS],
            travel: [0.0; 3],
        })
    }

    /// The parameters.
    #[must_use]
    pub const fn params(&self) -> &ChassisParams {
        &self.params
    }

    /// The substep used, s: `max_substep`.
    #[must_use]
    pub const fn substep(&self) -> f64 {
        self.substep
    }

    /// The state (ground truth).
    #[must_use]
    pub const fn state(&self) -> &ChassisState {
        &self.state
    }

    /// Replaces the state (e.g. to start at a pose or a velocity). The heading is
    /// `pose.heading` (wrapped); `yaw` is kept if it is the same angle unwrapped, else it
    /// restarts at the heading.
    ///
    /// # Errors
    /// [`ParamError`] if a value is not finite; the state is left unchanged.
    pub fn set_state(&mut self, state: ChassisState) -> Result<(), ParamError> {
        let s = &state;
        for (f, v) in [
            ("state.pose.x", s.pose.x),
            ("state.pose.y", s.pose.y),
            ("state.pose.heading", s.pose.heading),
            ("state.yaw", s.yaw),
            ("state.velocity.vx", s.velocity.vx),
            ("state.velocity.vy", s.velocity.vy),
            ("state.velocity.wz", s.velocity.wz),
        ] {
            finite(f, v)?;
        }
        for i in 0..WHEELS {
            finite("state.wheel_speed", s.wheel_speed[i]).map_err(|e| e.at(i))?;
            finite("state.wheel_angle", s.wheel_angle[i]).map_err(|e| e.at(i))?;
        }
        let pose = Pose2::new(state.pose.x, state.pose.y, state.pose.heading);
        let same = (wrap_angle(state.yaw) - pose.heading).abs() < 1e-9;
        self.state = ChassisState {
            pose,
            yaw: if same { state.yaw } else { pose.heading },
            ..state
        };
        Ok(())
    }

    /// The body-frame velocity integrated over time since the chassis was built,
    /// `(∫vx dt, ∫vy dt, ∫wz dt)` (m, m, rad), in the substeps the pose is integrated with:
    /// each substep adds its twist times its length, the twist the pose moves by.
    /// [`Self::set_state`] does not change it.
    ///
    /// Within a substep the twist is constant, so a point fixed on the body moves at a
    /// constant body-frame velocity: the distance it travels along a body-fixed direction
    /// `(cos φ, sin φ)` from `(x, y)` is exactly `cos φ (T_x − y T_ω) + sin φ (T_y + x T_ω)`
    /// for the difference `T` of two readings (what a tracking pod rolls, `crate::nodes::pods`).
    #[must_use]
    pub const fn body_travel(&self) -> [f64; 3] {
        self.travel
    }

    /// The contacts of the last substep.
    #[must_use]
    pub const fn contacts(&self) -> &[Contact; WHEELS] {
        &self.contacts
    }

    /// Changes the friction coefficient `μ` (fault injection: a slippery patch).
    ///
    /// # Errors
    /// [`ParamError`] unless `mu` is finite and `> 0`.
    pub fn set_friction(&mut self, mu: f64) -> Result<(), ParamError> {
        positive("chassis.friction", mu)?;
        let mut params = self.params;
        params.friction = mu;
        let loads = params.normal_loads();
        for (c, n) in self.consts.iter_mut().zip(loads) {
            c.mu_n = mu * n;
        }
        self.params = params;
        Ok(())
    }

    /// Kinetic energy of body and wheels, J.
    #[must_use]
    pub fn kinetic_energy(&self) -> f64 {
        let v = self.state.velocity;
        let body = 0.5 * self.params.mass * (v.vx * v.vx + v.vy * v.vy)
            + 0.5 * self.params.yaw_inertia * v.wz * v.wz;
        let wheels: f64 = (0..WHEELS)
            .map(|i| 0.5 * self.params.wheel_inertia[i] * self.state.wheel_speed[i].powi(2))
            .sum();
        body + wheels
    }

    /// The contact point and the roller-axis direction of wheel `i` at wheel angle `phi`.
    fn contact_geometry(&self, i: usize, phi: f64) -> (f64, f64, f64, f64) {
        let c = &self.consts[i];
        match &self.params.ripple {
            None => (c.ax, c.ay, c.eax, c.eay),
            Some(ripple) => {
                let u = ripple.local_angle(i, phi);
                let (sin_u, cos_u) = libm::sincos(u);
                // Eq. 11: the contact slides along the axle.
                let shift = -ripple.axis_offset * c.cot_d * sin_u / cos_u;
                // Eq. 10: ground projection of the tilted roller axis.
                let bx = c.cos_a * c.cos_d - c.sin_a * c.sin_d * cos_u;
                let by = c.sin_a * c.cos_d + c.cos_a * c.sin_d * cos_u;
                let n = (bx * bx + by * by).sqrt();
                (
                    c.ax + shift * c.cos_a,
                    c.ay + shift * c.sin_a,
                    bx / n,
                    by / n,
                )
            }
        }
    }

    /// Advances by `dt` seconds in equal substeps no longer than [`Self::substep`].
    ///
    /// # Errors
    /// [`ParamError`] if `dt` is negative, not finite or longer than a day (as
    /// [`Plant::step`](super::Plant::step)), or an input is not finite; the state is left
    /// unchanged.
    pub fn step(&mut self, dt: f64, inputs: &[WheelInput; WHEELS]) -> Result<(), ParamError> {
        non_negative("dt", dt)?;
        if dt > 86_400.0 {
            // Beyond, the substep count would not fit the loop's counter in any sane time.
            return Err(ParamError::new("dt", dt, "at most one day per step"));
        }
        for (i, input) in inputs.iter().enumerate() {
            let (WheelInput::Torque(v) | WheelInput::Speed(v)) = *input;
            finite("wheel_input", v).map_err(|e| e.at(i))?;
        }
        if dt == 0.0 {
            return Ok(());
        }
        let n = (dt / self.substep).ceil().max(1.0);
        let h = dt / n;
        // `n` is a small positive integer here (dt is finite, substep > 0).
        #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
        for _ in 0..(n as u64) {
            self.advance(h, inputs);
        }
        Ok(())
    }

    /// One substep of `h` seconds (`h` at most [`Self::substep`]; not checked): the
    /// linearly implicit step of `docs/simulator.md`, section "Chassis", "Integration".
    pub(crate) fn advance(&mut self, h: f64, inputs: &[WheelInput; WHEELS]) {
        let wz = self.state.velocity.wz;
        let (mut kb, mut rb, wheels) = self.assemble(h, inputs);
        // Eliminate the wheels: a held wheel's speed is known; a driven one is
        // ω = (r_w − c·v) / d_w, which folds its column into the body block.
        eliminate_wheels(&mut kb, &mut rb, &wheels);
        let [ux, uy, wz_new] = solve_spd3(&kb, rb);
        let wheel_speed = self.wheel_speeds_and_contacts(&wheels, [ux, uy, wz_new]);
        // The frame rotation ω × v as an exact rotation of the new body velocity by −ω h.
        let (sin_r, cos_r) = libm::sincos(-wz * h);
        let vx_new = cos_r * ux - sin_r * uy;
        let vy_new = sin_r * ux + cos_r * uy;

        let st = &mut self.state;
        st.velocity = ChassisVelocity::new(vx_new, vy_new, wz_new);
        st.wheel_speed = wheel_speed;
        for (a, w) in st.wheel_angle.iter_mut().zip(wheel_speed) {
            *a += h * w;
        }
        st.pose = st.pose.exp(Twist2::new(vx_new * h, vy_new * h, wz_new * h));
        st.yaw += wz_new * h;
        self.travel[0] += vx_new * h;
        self.travel[1] += vy_new * h;
        self.travel[2] += wz_new * h;
    }

    /// The system (M + h D) q⁺ = M q + h τ over q = (vx, vy, wz, ω_1..ω_4), in its arrowhead
    /// form: the body block `kb` (symmetric 3 × 3, upper triangle used), the rhs `rb`, and
    /// per wheel its coupling column, diagonal and rhs ([`WheelSystem`]).
    #[inline]
    fn assemble(
        &self,
        h: f64,
        inputs: &[WheelInput; WHEELS],
    ) -> ([[f64; 3]; 3], [f64; 3], [WheelSystem; WHEELS]) {
        let s = self.state;
        let (vx, vy, wz) = (s.velocity.vx, s.velocity.vy, s.velocity.wz);
        let (mass, inertia) = (self.params.mass, self.params.yaw_inertia);
        let eps = self.params.roller_drag;
        let s0_sq = self.params.slip_velocity * self.params.slip_velocity;
        let mut kb = [[mass, 0.0, 0.0], [0.0, mass, 0.0], [0.0, 0.0, inertia]];
        let rb = [mass * vx, mass * vy, inertia * wz];
        let mut wheels = [WheelSystem::default(); WHEELS];
        for (i, w) in wheels.iter_mut().enumerate() {
            let c = self.consts[i];
            let (cx, cy, eax, eay) = self.contact_geometry(i, s.wheel_angle[i]);
            let (efx, efy) = (-eay, eax);
            // Slip at the start of the step, for the frozen friction coefficient.
            let rim = c.r * s.wheel_speed[i];
            let sx = vx - wz * cy - rim * c.dx;
            let sy = vy + wz * cx - rim * c.dy;
            let sa = sx * eax + sy * eay;
            let wf = eps * (sx * efx + sy * efy);
            let k = c.mu_n / (sa * sa + wf * wf + s0_sq).sqrt();
            // h k A, A = e_a e_aᵀ + ε e_f e_fᵀ.
            let hk = h * k;
            let a11 = hk * (eax * eax + eps * efx * efx);
            let a12 = hk * (eax * eay + eps * efx * efy);
            let a22 = hk * (eay * eay + eps * efy * efy);
            // Body columns of the slip map: e1 = (1, 0), e2 = (0, 1), e3 = (−c_y, c_x);
            // the wheel column is b = −r d.
            let (a13, a23) = (-a11 * cy + a12 * cx, -a12 * cy + a22 * cx);
            kb[0][0] += a11;
            kb[0][1] += a12;
            kb[1][1] += a22;
            kb[0][2] += a13;
            kb[1][2] += a23;
            kb[2][2] += -cy * a13 + cx * a23;
            let (bx, by) = (-c.r * c.dx, -c.r * c.dy);
            let (p, q) = (a11 * bx + a12 * by, a12 * bx + a22 * by);
            *w = WheelSystem {
                geometry: [cx, cy, eax, eay],
                k,
                coupling: [p, q, -cy * p + cx * q],
                inv_diagonal: 1.0 / (c.j + bx * p + by * q),
                rhs: c.j * s.wheel_speed[i],
                held: None,
            };
            match inputs[i] {
                WheelInput::Torque(tau) => w.rhs += h * tau,
                WheelInput::Speed(speed) => w.held = Some(speed),
            }
        }
        (kb, rb, wheels)
    }

    /// The wheel speeds from the new body velocity `[ux, uy, wz]` (before the frame
    /// rotation), and each contact's force at them ([`Self::contacts`]).
    #[inline]
    fn wheel_speeds_and_contacts(
        &mut self,
        wheels: &[WheelSystem; WHEELS],
        [ux, uy, wz_new]: [f64; 3],
    ) -> [f64; WHEELS] {
        let eps = self.params.roller_drag;
        let mut wheel_speed = [0.0; WHEELS];
        for (i, w) in wheels.iter().enumerate() {
            let c = self.consts[i];
            let omega = w.held.unwrap_or_else(|| {
                (w.rhs - w.coupling[0] * ux - w.coupling[1] * uy - w.coupling[2] * wz_new)
                    * w.inv_diagonal
            });
            wheel_speed[i] = omega;
            // The force that acted: the frozen coefficient on the slip at the new velocities.
            let [cx, cy, eax, eay] = w.geometry;
            let (efx, efy) = (-eay, eax);
            let rim = c.r * omega;
            let sx = ux - wz_new * cy - rim * c.dx;
            let sy = uy + wz_new * cx - rim * c.dy;
            let sa = sx * eax + sy * eay;
            let sf = sx * efx + sy * efy;
            let k = -w.k;
            let f = [
                k * (sa * eax + eps * sf * efx),
                k * (sa * eay + eps * sf * efy),
            ];
            self.contacts[i] = Contact {
                position: [cx, cy],
                force: f,
                slip_axial: sa,
                slip_free: sf,
                load_torque: c.r * (f[0] * c.dx + f[1] * c.dy),
            };
        }
        wheel_speed
    }
}

/// Folds the wheels' rows of the arrowhead system into the body block `kb` and rhs `rb`: a
/// held wheel's speed is known, a driven one's is `ω = (r_w − c·v) / d_w`.
#[inline]
fn eliminate_wheels(kb: &mut [[f64; 3]; 3], rb: &mut [f64; 3], wheels: &[WheelSystem; WHEELS]) {
    for w in wheels {
        let c = w.coupling;
        match w.held {
            Some(speed) => {
                for (r, cj) in rb.iter_mut().zip(c) {
                    *r -= cj * speed;
                }
            }
            None => {
                let inv = w.inv_diagonal;
                for j in 0..3 {
                    rb[j] -= c[j] * w.rhs * inv;
                    for l in j..3 {
                        kb[j][l] -= c[j] * c[l] * inv;
                    }
                }
            }
        }
    }
}

/// One wheel's rows of the implicit system (see [`Chassis::advance`]).
#[derive(Debug, Clone, Copy, Default)]
struct WheelSystem {
    /// Contact point and roller axis `[c_x, c_y, e_ax, e_ay]`.
    geometry: [f64; 4],
    /// The frozen friction coefficient `k = μN / sqrt(s_a² + ε² s_f² + s0²)`.
    k: f64,
    /// The wheel's column against the body velocities.
    coupling: [f64; 3],
    /// The wheel's diagonal entry `J + h k bᵀ A b`, inverted.
    inv_diagonal: f64,
    /// The wheel's right-hand side `J ω + h τ`.
    rhs: f64,
    /// The speed of a wheel held by an ideal servo.
    held: Option<f64>,
}

/// Solves `K x = r` for a symmetric positive definite 3 × 3 `K` (upper triangle used) by
/// Cholesky factorisation.
fn solve_spd3(k: &[[f64; 3]; 3], r: [f64; 3]) -> [f64; 3] {
    // The inverses of the diagonal of L: three divisions instead of nine.
    let i00 = 1.0 / k[0][0].sqrt();
    let l10 = k[0][1] * i00;
    let l20 = k[0][2] * i00;
    let i11 = 1.0 / (k[1][1] - l10 * l10).sqrt();
    let l21 = (k[1][2] - l20 * l10) * i11;
    let i22 = 1.0 / (k[2][2] - l20 * l20 - l21 * l21).sqrt();
    let y0 = r[0] * i00;
    let y1 = (r[1] - l10 * y0) * i11;
    let y2 = (r[2] - l20 * y0 - l21 * y1) * i22;
    let x2 = y2 * i22;
    let x1 = (y1 - l21 * x2) * i11;
    let x0 = (y0 - l10 * x1 - l20 * x2) * i00;
    [x0, x1, x2]
}
