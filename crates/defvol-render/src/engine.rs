//! The raycasters on the run's backend, one interface per picture: [`VolumeRenderer`] over a
//! volume (on the host, or a device buffer the GPU warp rewrites) and [`MeshRenderer`] over
//! the deformed tets (positions from the host, or placed on the device by another stage).

use std::sync::Arc;

use nalgebra::Vector3;

use super::camera::Camera;
use super::mesh::TetRaycaster;
use super::transfer::Tables;
use super::volume::{RaycastParams, ToolPicture, VolumeRaycaster};
use super::{RenderError, Rendered};
use defvol_core::volume::Volume;
use defvol_gpu::backend::{Backend, BackendError, RunsOn};

#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum RenderEngineError {
    #[error(transparent)]
    Render(#[from] RenderError),
    #[error(transparent)]
    Backend(#[from] BackendError),
    #[cfg(feature = "gpu")]
    #[error(transparent)]
    Gpu(#[from] super::volume::gpu::GpuRenderError),
    #[error("the CPU raycaster needs the volume on the host")]
    NoHostVolume,
}

/// The volume a frame shows.
pub enum Shown<'a> {
    /// On the host (the CPU path reads it; the GPU path was given its own at creation).
    Host(&'a Volume),
    /// On the device, where the GPU path was pointed at creation.
    Device,
}

pub enum VolumeRenderer {
    /// Tables built once; each frame prepares the macro cells of the volume it is given.
    Cpu { tables: Arc<Tables>, params: RaycastParams },
    #[cfg(feature = "gpu")]
    Gpu(Box<super::volume::gpu::GpuVolumeRaycaster>),
}

impl VolumeRenderer {
    /// A raycaster of `volume` (GPU: uploaded once) with `tables` built for `params`.
    pub fn new(
        backend: &Backend,
        volume: &Volume,
        tables: Arc<Tables>,
        params: &RaycastParams,
    ) -> Result<Self, RenderEngineError> {
        // Prepared here so that a bad parameter fails at start, not mid-run.
        let prepared = VolumeRaycaster::with_tables(volume, tables.clone(), params)?;
        #[cfg(feature = "gpu")]
        if let Some(gpu) =
            backend.try_gpu("raycast", |ctx| super::volume::gpu::GpuVolumeRaycaster::new(ctx.clone(), &prepared))?
        {
            return Ok(Self::Gpu(Box::new(gpu)));
        }
        #[cfg(not(feature = "gpu"))]
        let _ = backend;
        drop(prepared);
        Ok(Self::Cpu { tables, params: params.clone() })
    }

    /// On the GPU, a raycaster reading `samples`, a device buffer on `volume`'s grid that
    /// another stage rewrites (the GPU warp's output); the tables' range is `volume`'s.
    #[cfg(feature = "gpu")]
    pub fn on_device(
        ctx: Arc<defvol_gpu::gpu::GpuContext>,
        samples: wgpu::Buffer,
        volume: &Volume,
        tables: &Tables,
        params: &RaycastParams,
    ) -> Result<Self, RenderEngineError> {
        let gpu = super::volume::gpu::GpuVolumeRaycaster::on_device(
            ctx,
            samples,
            &volume.grid(),
            volume.range(),
            tables,
            params,
        )?;
        Ok(Self::Gpu(Box::new(gpu)))
    }

    /// Where this stage runs.
    pub fn runs_on(&self) -> RunsOn {
        match self {
            Self::Cpu { .. } => RunsOn::Cpu,
            #[cfg(feature = "gpu")]
            Self::Gpu(_) => RunsOn::Gpu,
        }
    }

    /// After another stage rewrote the device volume (GPU; nothing on the CPU).
    pub fn volume_changed(&self) {
        #[cfg(feature = "gpu")]
        if let Self::Gpu(g) = self {
            g.volume_changed();
        }
    }

    /// One frame of `shown` with `tools`, seen by `camera`.
    pub fn render(
        &mut self,
        shown: Shown<'_>,
        tools: &[ToolPicture],
        camera: &Camera,
    ) -> Result<Rendered, RenderEngineError> {
        match self {
            Self::Cpu { tables, params } => {
                let Shown::Host(volume) = shown else { return Err(RenderEngineError::NoHostVolume) };
                params.tools = tools.to_vec();
                Ok(VolumeRaycaster::with_tables(volume, tables.clone(), params)?.render(camera)?)
            }
            #[cfg(feature = "gpu")]
            Self::Gpu(g) => {
                g.set_tools(tools)?;
                Ok(g.render(camera)?)
            }
        }
    }
}

pub enum MeshRenderer {
    Cpu(Box<TetRaycaster>),
    #[cfg(feature = "gpu")]
    Gpu(Box<super::mesh::gpu::GpuTetRaycaster>),
}

impl MeshRenderer {
    /// The prepared mesh raycaster on `backend`. Its positions at creation are the rest
    /// that displacements are taken from; `to_file` scales the displacements other stages
    /// place on the device to the mesh's units.
    pub fn new(backend: &Backend, prepared: TetRaycaster, to_file: f64) -> Result<Self, RenderEngineError> {
        #[cfg(feature = "gpu")]
        if let Some(gpu) =
            backend.try_gpu("raycast", |ctx| super::mesh::gpu::GpuTetRaycaster::new(ctx.clone(), &prepared, to_file))?
        {
            return Ok(Self::Gpu(Box::new(gpu)));
        }
        #[cfg(not(feature = "gpu"))]
        let _ = (backend, to_file);
        Ok(Self::Cpu(Box::new(prepared)))
    }

    /// Where this stage runs.
    pub fn runs_on(&self) -> RunsOn {
        match self {
            Self::Cpu(_) => RunsOn::Cpu,
            #[cfg(feature = "gpu")]
            Self::Gpu(_) => RunsOn::Gpu,
        }
    }

    /// On the GPU: where another stage places the deformed nodes (then [`Self::refresh`]).
    #[cfg(feature = "gpu")]
    pub fn device_nodes(&self) -> Option<&Arc<defvol_gpu::gpu::DeviceNodes>> {
        match self {
            Self::Gpu(g) => Some(g.nodes()),
            Self::Cpu(_) => None,
        }
    }

    /// New positions from the host (the mesh's units).
    pub fn update(&mut self, positions: &[Vector3<f64>]) -> Result<(), RenderEngineError> {
        match self {
            Self::Cpu(c) => c.update(positions)?,
            #[cfg(feature = "gpu")]
            Self::Gpu(g) => g.update(positions)?,
        }
        Ok(())
    }

    /// After another stage placed the nodes on the device (GPU; nothing on the CPU).
    pub fn refresh(&self) {
        #[cfg(feature = "gpu")]
        if let Self::Gpu(g) = self {
            g.refresh();
        }
    }

    pub fn render(&mut self, tools: &[ToolPicture], camera: &Camera) -> Result<Rendered, RenderEngineError> {
        match self {
            Self::Cpu(c) => {
                c.set_tools(tools.to_vec())?;
                Ok(c.render(camera)?)
            }
            #[cfg(feature = "gpu")]
            Self::Gpu(g) => {
                g.set_tools(tools)?;
                Ok(g.render(camera)?)
            }
        }
    }
}
