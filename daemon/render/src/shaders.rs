//! The WGSL kernels, one per file in `shaders/`, and their shared includes.
//!
//! A kernel file pulls an include with a line `//#include NAME.wgsl`; [`source`] splices the
//! include in its place (once per kernel). Each kernel is declared once here; the `shaders` tests
//! parse and validate every kernel with naga, so a broken shader fails `cargo test` rather than the
//! first render.

/// Every shader of the renderer: the compute kernels and the presentation pass. One name per
/// concept: `Kernel::Isosurface` is `shaders/isosurface.wgsl` and `gpu/isosurface.rs`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kernel {
    Isosurface,
    Ao,
    /// The tile's presentable image: colour, accumulation, sRGB, upsample (its own parameters,
    /// `ComposeParams`, not the frame's).
    Compose,
    /// The edge-aware spatial filter of the occlusion and IBL terms, one a-trous pass per dispatch
    /// (its own parameters, `DenoiseParams`).
    Denoise,
    /// A tile's running sums carried over from its previous frame where only the camera moved
    /// (its own parameters, `ReprojectParams`).
    Reproject,
    /// Not a compute kernel: the render pass that draws a tile's image into its window.
    Present,
}

impl Kernel {
    pub const ALL: [Kernel; 6] = [
        Kernel::Isosurface,
        Kernel::Ao,
        Kernel::Compose,
        Kernel::Denoise,
        Kernel::Reproject,
        Kernel::Present,
    ];
    /// The compute kernels (entry point `main`).
    pub const COMPUTE: [Kernel; 5] =
        [Kernel::Isosurface, Kernel::Ao, Kernel::Compose, Kernel::Denoise, Kernel::Reproject];
    /// The kernels that read the frame parameters of `frame.wgsl`.
    pub const FRAME: [Kernel; 2] = [Kernel::Isosurface, Kernel::Ao];

    pub fn file_name(self) -> &'static str {
        match self {
            Kernel::Isosurface => "isosurface.wgsl",
            Kernel::Ao => "ao.wgsl",
            Kernel::Compose => "compose.wgsl",
            Kernel::Denoise => "denoise.wgsl",
            Kernel::Reproject => "reproject.wgsl",
            Kernel::Present => "present.wgsl",
        }
    }

    /// The entry points the host uses.
    pub fn entry_points(self) -> &'static [&'static str] {
        match self {
            Kernel::Isosurface | Kernel::Ao | Kernel::Compose | Kernel::Denoise | Kernel::Reproject => {
                &["main"]
            }
            Kernel::Present => &["vs_main", "fs_main"],
        }
    }

    fn raw(self) -> &'static str {
        match self {
            Kernel::Isosurface => include_str!("../../../shaders/isosurface.wgsl"),
            Kernel::Ao => include_str!("../../../shaders/ao.wgsl"),
            Kernel::Compose => include_str!("../../../shaders/compose.wgsl"),
            Kernel::Denoise => include_str!("../../../shaders/denoise.wgsl"),
            Kernel::Reproject => include_str!("../../../shaders/reproject.wgsl"),
            Kernel::Present => include_str!("../../../shaders/present.wgsl"),
        }
    }
}

/// Shared include files, by name.
const INCLUDES: &[(&str, &str)] = &[
    ("camera.wgsl", include_str!("../../../shaders/camera.wgsl")),
    ("hit.wgsl", include_str!("../../../shaders/hit.wgsl")),
    ("frame.wgsl", include_str!("../../../shaders/frame.wgsl")),
    ("sampling.wgsl", include_str!("../../../shaders/sampling.wgsl")),
    ("environment.wgsl", include_str!("../../../shaders/environment.wgsl")),
    ("volume.wgsl", include_str!("../../../shaders/volume.wgsl")),
    ("shading.wgsl", include_str!("../../../shaders/shading.wgsl")),
];

/// The text of a shared include (`sampling.wgsl`, ...), for tests that run one on the GPU.
pub fn include(name: &str) -> Option<&'static str> {
    INCLUDES.iter().find(|(n, _)| *n == name).map(|(_, text)| *text)
}

/// The complete WGSL of a kernel, includes spliced in.
pub fn source(kernel: Kernel) -> String {
    let mut out = String::new();
    for line in kernel.raw().lines() {
        if let Some(name) = line.trim().strip_prefix("//#include ") {
            let name = name.trim();
            let Some((_, text)) = INCLUDES.iter().find(|(n, _)| *n == name) else {
                panic!("{}: unknown include '{name}'", kernel.file_name());
            };
            out.push_str(&format!("// ---- begin {name}\n{text}\n// ---- end {name}\n"));
        } else {
            out.push_str(line);
            out.push('\n');
        }
    }
    out
}

/// The WGSL a compute kernel declares its workgroup shape with; [`source_with_workgroup`] replaces it.
pub const WORKGROUP_DECLARATION: &str = "@workgroup_size(8, 8, 1)";

/// A compute kernel's WGSL with workgroup shape (x, y) instead of the declared 8x8.
pub fn source_with_workgroup(kernel: Kernel, workgroup: (u32, u32)) -> String {
    let src = source(kernel);
    if kernel == Kernel::Present {
        return src;
    }
    assert!(
        src.contains(WORKGROUP_DECLARATION),
        "{} declares no {WORKGROUP_DECLARATION}",
        kernel.file_name()
    );
    src.replace(WORKGROUP_DECLARATION, &format!("@workgroup_size({}, {}, 1)", workgroup.0, workgroup.1))
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// What a binding holds, as a layout entry or naga's reflection of the WGSL says.
    #[derive(Debug, PartialEq)]
    enum BindingKind {
        Storage { read_only: bool },
        Uniform,
        StorageTexture,
        Texture,
        Sampler,
    }

    /// The bindings of group 0 that `kernel`'s WGSL declares, by naga.
    fn reflected(kernel: Kernel) -> std::collections::BTreeMap<u32, BindingKind> {
        let module = parse(kernel);
        module
            .global_variables
            .iter()
            .filter_map(|(_, g)| {
                let rb = g.binding.as_ref()?;
                assert_eq!(rb.group, 0, "{}: group {}", kernel.file_name(), rb.group);
                let kind = match g.space {
                    naga::AddressSpace::Storage { access } => {
                        BindingKind::Storage { read_only: !access.contains(naga::StorageAccess::STORE) }
                    }
                    naga::AddressSpace::Uniform => BindingKind::Uniform,
                    _ => match module.types[g.ty].inner {
                        naga::TypeInner::Image { class: naga::ImageClass::Storage { .. }, .. } => {
                            BindingKind::StorageTexture
                        }
                        naga::TypeInner::Image { .. } => BindingKind::Texture,
                        naga::TypeInner::Sampler { .. } => BindingKind::Sampler,
                        ref other => panic!("{}: binding {} is a {other:?}", kernel.file_name(), rb.binding),
                    },
                };
                Some((rb.binding, kind))
            })
            .collect()
    }

    /// The bindings a layout's entries declare.
    fn declared(entries: &[wgpu::BindGroupLayoutEntry]) -> std::collections::BTreeMap<u32, BindingKind> {
        entries
            .iter()
            .map(|e| {
                let kind = match e.ty {
                    wgpu::BindingType::Buffer {
                        ty: wgpu::BufferBindingType::Storage { read_only }, ..
                    } => BindingKind::Storage { read_only },
                    wgpu::BindingType::Buffer { ty: wgpu::BufferBindingType::Uniform, .. } => {
                        BindingKind::Uniform
                    }
                    wgpu::BindingType::StorageTexture { .. } => BindingKind::StorageTexture,
                    wgpu::BindingType::Texture { .. } => BindingKind::Texture,
                    wgpu::BindingType::Sampler(_) => BindingKind::Sampler,
                    ref other => panic!("binding {}: {other:?}", e.binding),
                };
                (e.binding, kind)
            })
            .collect()
    }

    #[test]
    fn every_compute_kernels_bind_group_layout_is_what_its_wgsl_declares() {
        use crate::gpu::{
            ao::AoKernel, compose::ComposeKernel, denoise::DenoiseKernel, isosurface::IsosurfaceKernel,
            reproject::ReprojectKernel,
        };
        for (kernel, entries) in [
            (Kernel::Isosurface, IsosurfaceKernel::entries()),
            (Kernel::Ao, AoKernel::entries()),
            (Kernel::Compose, ComposeKernel::entries()),
            (Kernel::Denoise, DenoiseKernel::entries()),
            (Kernel::Reproject, ReprojectKernel::entries()),
        ] {
            assert_eq!(declared(&entries), reflected(kernel), "{}", kernel.file_name());
        }
    }

    #[test]
    fn the_present_pipelines_bind_group_layout_is_what_present_wgsl_declares() {
        let entries = crate::gpu::present::entries();
        assert_eq!(declared(&entries), reflected(Kernel::Present), "{}", Kernel::Present.file_name());
    }

    /// The u32 value of every named module-scope `const` of `kernel`'s WGSL.
    pub(crate) fn wgsl_constants(kernel: Kernel) -> std::collections::BTreeMap<String, u32> {
        let module = parse(kernel);
        module
            .constants
            .iter()
            .filter_map(|(_, c)| match module.global_expressions[c.init] {
                naga::Expression::Literal(naga::Literal::U32(v)) => Some((c.name.clone()?, v)),
                _ => None,
            })
            .collect()
    }

    /// Parses and validates a kernel with naga, panicking with the shader's own diagnostics.
    pub(crate) fn parse(kernel: Kernel) -> naga::Module {
        let src = source(kernel);
        let module = naga::front::wgsl::parse_str(&src)
            .unwrap_or_else(|e| panic!("{}: {}", kernel.file_name(), e.emit_to_string(&src)));
        naga::valid::Validator::new(
            naga::valid::ValidationFlags::all(),
            naga::valid::Capabilities::default(),
        )
        .validate(&module)
        .unwrap_or_else(|e| panic!("{}: {}", kernel.file_name(), e.emit_to_string(&src)));
        module
    }

    #[test]
    fn every_kernel_parses_and_validates() {
        for k in Kernel::ALL {
            let m = parse(k);
            for name in k.entry_points() {
                assert!(m.entry_points.iter().any(|e| e.name == *name), "{} has no `{name}`", k.file_name());
            }
        }
    }

    #[test]
    fn workgroup_shapes_replace_the_declaration_and_validate() {
        for k in Kernel::COMPUTE {
            let src = source_with_workgroup(k, (16, 4));
            assert!(src.contains("@workgroup_size(16, 4, 1)") && !src.contains(WORKGROUP_DECLARATION));
            let module = naga::front::wgsl::parse_str(&src).expect("parses");
            let ep = module.entry_points.iter().find(|e| e.name == "main").expect("main");
            assert_eq!(ep.workgroup_size, [16, 4, 1]);
        }
    }

    #[test]
    fn every_include_is_used_and_spliced_once() {
        for (name, text) in INCLUDES {
            let used = Kernel::ALL.iter().any(|&k| source(k).contains(&format!("// ---- begin {name}")));
            assert!(used, "include {name} is not used by any kernel");
            assert!(!text.contains("//#include"), "{name}: includes do not nest");
        }
    }

    /// Checks a `#[repr(C)]` twin against the WGSL struct of the same name: every member's offset
    /// and the total size. `members` lists (WGSL member name, Rust offset, Rust size of the field).
    pub(crate) fn check_layout(kernel: Kernel, name: &str, rust_size: usize, members: &[(&str, usize)]) {
        let module = parse(kernel);
        let (ty_handle, ty) = module
            .types
            .iter()
            .find(|(_, t)| t.name.as_deref() == Some(name))
            .unwrap_or_else(|| panic!("{}: no struct {name}", kernel.file_name()));
        let naga::TypeInner::Struct { members: wgsl, span } = &ty.inner else {
            panic!("{name} is not a struct");
        };
        let _ = ty_handle;
        assert_eq!(*span as usize, rust_size, "{name}: WGSL size {span} != Rust size {rust_size}");
        assert_eq!(
            wgsl.len(),
            members.len(),
            "{name}: WGSL has {} members, Rust {}",
            wgsl.len(),
            members.len()
        );
        for (m, (rname, roff)) in wgsl.iter().zip(members) {
            assert_eq!(m.name.as_deref(), Some(*rname), "{name}: member order differs");
            assert_eq!(
                m.offset as usize, *roff,
                "{name}.{rname}: WGSL offset {} != Rust offset {roff}",
                m.offset
            );
        }
    }
}
