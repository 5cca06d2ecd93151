// ViSP's photometric visual servoing (vpFeatureLuminance, vpServo's eye-in-hand law) on vpImageSimulator renders of a finite
// textured plane, from given starts: the ViSP side of benchmarks/visp_domain.py (which compiles this file with
// g++ and `pkg-config visp` at run time and feeds it the same starts, camera and texture as the domain sweep).
//
// Input (stdin, whitespace-separated):
//   texture_path                               grey image (PGM) glued on the plane, row 0 at y = -h/2
//   width height fx fy cx cy                   camera (pixels, principal point in pixel-centre coordinates)
//   w h                                        textured extent of the plane (m), centred on the object frame
//   Z lambda dt max_images max_linear max_angular stop_velocity background
//   cdMo (16 numbers, row-major)               goal pose of the object in the camera frame
//   n, then n × cMo (16 numbers each)          start poses
// Output (stdout): one line per start: "images reason" then the final cMo (16 numbers, row-major); reason is
// "converged" (‖v‖ < stop_velocity and ‖ω‖ < stop_velocity), "diverged" (camera outside 0.2–3 m of the target
// centre) or "budget".
// Control: vpServo's EYEINHAND_CAMERA law with the interaction matrix at the goal (vpServo::DESIRED; constant depth
// Z, the true depth of a fronto-parallel plane at the goal), v = −λ L*⁺ (I − I*), written out with L*⁺ computed
// once: vpServo::computeControlLaw recomputes the pseudo-inverse of the N×6 matrix (N ≈ 210 000 pixels) at every
// image, the same matrix, which costs more than the shared machine can give. v is scaled down to the velocity
// limits as in the ddvs service and applied exactly over dt (cMo ← exp(v dt)⁻¹ cMo).
#include <cmath>
#include <iostream>
#include <string>
#include <vector>

#include <visp3/core/vpCameraParameters.h>
#include <visp3/core/vpExponentialMap.h>
#include <visp3/core/vpHomogeneousMatrix.h>
#include <visp3/core/vpImage.h>
#include <visp3/io/vpImageIo.h>
#include <visp3/robot/vpImageSimulator.h>
#include <visp3/visual_features/vpFeatureLuminance.h>

static vpHomogeneousMatrix read_pose(std::istream &in)
{
  vpHomogeneousMatrix M;
  for (unsigned int i = 0; i < 4; i++)
    for (unsigned int j = 0; j < 4; j++)
      in >> M[i][j];
  return M;
}

static void write_pose(const vpHomogeneousMatrix &M)
{
  for (unsigned int i = 0; i < 4; i++)
    for (unsigned int j = 0; j < 4; j++)
      std::cout << ' ' << M[i][j];
}

int main()
{
  std::string texture_path;
  unsigned int width, height, max_images, n;
  double fx, fy, cx, cy, w, h, Z, lambda, dt, max_linear, max_angular, stop_velocity, background;
  std::cin >> texture_path >> width >> height >> fx >> fy >> cx >> cy >> w >> h;
  std::cin >> Z >> lambda >> dt >> max_images >> max_linear >> max_angular >> stop_velocity >> background;
  if (!std::cin) {
    std::cerr << "bad header: expected texture, camera, extent and control settings (see the file's comment)\n";
    return 2;
  }
  vpHomogeneousMatrix cdMo = read_pose(std::cin);
  std::cin >> n;
  std::vector<vpHomogeneousMatrix> starts;
  for (unsigned int k = 0; k < n; k++)
    starts.push_back(read_pose(std::cin));
  if (!std::cin) {
    std::cerr << "bad poses: expected the goal, a count and that many 4x4 row-major poses\n";
    return 2;
  }

  vpImage<unsigned char> texture;
  vpImageIo::read(texture, texture_path);
  vpColVector X[4];
  const double corners[4][2] = {{-w / 2, -h / 2}, {w / 2, -h / 2}, {w / 2, h / 2}, {-w / 2, h / 2}};
  for (int i = 0; i < 4; i++) {
    X[i].resize(3);
    X[i][0] = corners[i][0];
    X[i][1] = corners[i][1];
    X[i][2] = 0.0;
  }
  vpImageSimulator sim;
  sim.setInterpolationType(vpImageSimulator::BILINEAR_INTERPOLATION);
  const unsigned char grey = static_cast<unsigned char>(background);
  sim.setCleanPreviousImage(true, vpColor(grey, grey, grey));
  sim.init(texture, X);
  // ViSP's pixel coordinates have pixel centres at integers, like ours.
  vpCameraParameters cam(fx, fy, cx, cy);

  vpImage<unsigned char> Id(height, width, grey), I(height, width, grey);
  sim.setCameraPosition(cdMo);
  sim.getImage(Id, cam);
  vpFeatureLuminance sId;
  sId.init(height, width, Z);
  sId.setCameraParameters(cam);
  sId.buildFrom(Id);
  vpMatrix Lsd, Lsd_pinv;
  sId.interaction(Lsd);
  Lsd.pseudoInverse(Lsd_pinv, 1e-6);

  for (const vpHomogeneousMatrix &start : starts) {
    vpHomogeneousMatrix cMo = start;
    vpFeatureLuminance sI;
    sI.init(height, width, Z);
    sI.setCameraParameters(cam);
    vpColVector error;
    std::string reason = "budget";
    unsigned int images = 0;
    while (images < max_images) {
      images++;
      sim.setCameraPosition(cMo);
      sim.getImage(I, cam);
      sI.buildFrom(I);
      sI.error(sId, error);
      vpColVector v = -lambda * (Lsd_pinv * error);
      double lin = std::sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
      double ang = std::sqrt(v[3] * v[3] + v[4] * v[4] + v[5] * v[5]);
      if (lin < stop_velocity && ang < stop_velocity) {
        reason = "converged";
        break;
      }
      vpHomogeneousMatrix oMc = cMo.inverse();
      double distance = std::sqrt(oMc[0][3] * oMc[0][3] + oMc[1][3] * oMc[1][3] + oMc[2][3] * oMc[2][3]);
      if (distance < 0.2 || distance > 3.0) {
        reason = "diverged";
        break;
      }
      double scale = std::min(1.0, std::min(max_linear / std::max(lin, 1e-300), max_angular / std::max(ang, 1e-300)));
      cMo = vpExponentialMap::direct(v * scale, dt).inverse() * cMo;
    }
    std::cout << images << ' ' << reason;
    write_pose(cMo);
    std::cout << std::endl;
  }
  return 0;
}
