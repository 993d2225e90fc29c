"""Image formation: the forward model every fitter and simulation uses.

``psf`` (Gaussian and measured kernels), ``trajectory`` (sine, multisine, spline), ``window``
(exposure windows and sensor timing), ``blur`` (:func:`render_blur`, :class:`BlurRenderer`),
``splat`` (the image with its Jacobian), ``coded`` (coded exposures), ``alias`` (Proposition 3),
``camera`` (a simulated camera). Imports torch and numpy only.
"""
from torchblur.render.alias import alias_phase, window_center_phase, wrap_phase
from torchblur.render.blur import BlurRenderer, RenderSettings, choose_node_count, quadrature_nodes, render_blur
from torchblur.render.camera import CameraModel
from torchblur.render.coded import check_code, coded_windows, mirror_code, render_coded
from torchblur.render.psf import GaussianPSF, KernelPSF
from torchblur.render.splat import gaussian_splat_with_jacobian
from torchblur.render.trajectory import Multisine, Sinusoid, SplineTrajectory, Trajectory
from torchblur.render.window import ExposureWindow, SensorTiming

__all__ = [
    "BlurRenderer", "CameraModel", "ExposureWindow", "GaussianPSF", "KernelPSF", "Multisine", "RenderSettings",
    "SensorTiming", "Sinusoid", "SplineTrajectory", "Trajectory", "alias_phase", "check_code", "choose_node_count",
    "coded_windows", "gaussian_splat_with_jacobian", "mirror_code", "quadrature_nodes", "render_blur", "render_coded",
    "window_center_phase", "wrap_phase",
]
