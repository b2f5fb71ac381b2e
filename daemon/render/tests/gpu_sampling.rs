//! The WGSL sample patterns (shaders/sampling.wgsl) against their CPU twin (src/sampling.rs), on
//! the GPU: the R2 and Owen-scrambled Sobol points bit for bit, the cosine directions to f32
//! rounding. The renderers then draw the same directions for the same pixel and frame.

mod common;

use glam::DVec3;
use isowall_render::sampling::{cosine_direction, pixel_key, r2_point, sobol_point};
use isowall_render::shaders;
use wgpu::util::DeviceExt;

const PER_KEY: u32 = 1024;

#[test]
fn gpu_sample_points_are_the_cpu_points_bit_for_bit() {
    let Some(gpu) = common::gpu() else { return };
    let (device, queue) = (&gpu.ctx.device, &gpu.ctx.queue);
    let keys: Vec<u32> = (0..16u32)
        .map(|k| pixel_key(37 * k + 1, 11 * k, k % 5, 3))
        .chain([0, 1, u32::MAX, 0x8000_0000])
        .collect();
    let normal = DVec3::new(0.3, -0.5, 0.81).normalize();
    let src = format!(
        "{}\n{}",
        shaders::include("sampling.wgsl").expect("sampling.wgsl"),
        r#"
@group(0) @binding(0) var<storage, read> keys: array<u32>;
@group(0) @binding(1) var<storage, read_write> points: array<vec4<u32>>;
@group(0) @binding(2) var<storage, read_write> dirs: array<vec4<f32>>;
@compute @workgroup_size(64, 1, 1)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let idx = gid.x;
    if idx >= arrayLength(&keys) * 1024u {
        return;
    }
    let key = keys[idx / 1024u];
    let i = idx % 1024u;
    let r = r2_point(i, key);
    let s = sobol_point(i, key);
    points[idx] = vec4<u32>(bitcast<u32>(r.x), bitcast<u32>(r.y), bitcast<u32>(s.x), bitcast<u32>(s.y));
    let n = normalize(vec3<f32>(0.3, -0.5, 0.81));
    dirs[idx] = vec4<f32>(cosine_direction(n, onb(n), s), 0.0);
}
"#
    );
    let n = keys.len() as u64 * PER_KEY as u64;
    let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some("sampling test"),
        source: wgpu::ShaderSource::Wgsl(src.into()),
    });
    let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
        label: Some("sampling test"),
        layout: None,
        module: &module,
        entry_point: Some("main"),
        compilation_options: Default::default(),
        cache: None,
    });
    let storage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC;
    let key_buf = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: Some("keys"),
        contents: bytemuck::cast_slice(&keys),
        usage: wgpu::BufferUsages::STORAGE,
    });
    let make = |label, usage| {
        device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size: n * 16,
            usage,
            mapped_at_creation: false,
        })
    };
    let (points, dirs) = (make("points", storage), make("dirs", storage));
    let read = wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST;
    let (points_r, dirs_r) = (make("points read", read), make("dirs read", read));
    let bind = device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some("sampling test"),
        layout: &pipeline.get_bind_group_layout(0),
        entries: &[
            wgpu::BindGroupEntry { binding: 0, resource: key_buf.as_entire_binding() },
            wgpu::BindGroupEntry { binding: 1, resource: points.as_entire_binding() },
            wgpu::BindGroupEntry { binding: 2, resource: dirs.as_entire_binding() },
        ],
    });
    let mut enc = device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: None });
    {
        let mut pass =
            enc.begin_compute_pass(&wgpu::ComputePassDescriptor { label: None, timestamp_writes: None });
        pass.set_pipeline(&pipeline);
        pass.set_bind_group(0, &bind, &[]);
        pass.dispatch_workgroups(keys.len() as u32 * PER_KEY / 64, 1, 1);
    }
    enc.copy_buffer_to_buffer(&points, 0, &points_r, 0, None);
    enc.copy_buffer_to_buffer(&dirs, 0, &dirs_r, 0, None);
    queue.submit([enc.finish()]);
    for b in [&points_r, &dirs_r] {
        b.map_async(wgpu::MapMode::Read, .., |r| r.expect("map"));
    }
    device.poll(wgpu::PollType::wait_indefinitely()).expect("poll");
    let p = points_r.get_mapped_range(..).expect("mapped").to_vec();
    let d = dirs_r.get_mapped_range(..).expect("mapped").to_vec();
    let p: &[[u32; 4]] = bytemuck::cast_slice(&p);
    let d: &[[f32; 4]] = bytemuck::cast_slice(&d);
    let mut worst = 0f64;
    for (k, &key) in keys.iter().enumerate() {
        for i in 0..PER_KEY {
            let idx = k * PER_KEY as usize + i as usize;
            let (r, s) = (r2_point(i, key), sobol_point(i, key));
            let want = [r.0.to_bits(), r.1.to_bits(), s.0.to_bits(), s.1.to_bits()];
            assert_eq!(p[idx], want, "key {key:#x} sample {i}: GPU {:?} CPU {want:?}", p[idx]);
            let w = cosine_direction(normal, s.0, s.1);
            let g = DVec3::new(d[idx][0] as f64, d[idx][1] as f64, d[idx][2] as f64);
            worst = worst.max((g - w).length());
        }
    }
    assert!(worst < 2e-6, "cosine directions differ by {worst}");
}
