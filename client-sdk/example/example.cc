// The smallest libprism_client program: opens a session, streams N synthetic grey frames, prints the
// poses and chunks it gets, closes and prints the summary.
//   prism_client_example tcp://127.0.0.1:5555 [frames]
#include <prism/client/client.h>

#include <cstdio>
#include <cstdlib>
#include <vector>

int main(int argc, char** argv) {
  if (argc < 2) {
    std::fprintf(stderr, "usage: prism_client_example tcp://HOST:PORT [frames]\n");
    return 2;
  }
  const int frames = argc > 2 ? std::atoi(argv[2]) : 10;
  prism::client::Rig rig;
  rig.camera = {160, 120, 150, 150, 80, 60, {0, 0, 0, 0, 0}};
  const char* names[3] = {"red", "green", "blue"};
  const double x[3] = {-0.2, 0.2, 0.0}, y[3] = {0.0, 0.0, -0.2};
  for (int l = 0; l < 3; ++l) {
    rig.lights[l].name = names[l];
    rig.lights[l].position_in_camera = {x[l], y[l], 0.0};
    rig.lights[l].color = {l == 0 ? 1.0 : 0.0, l == 1 ? 1.0 : 0.0, l == 2 ? 1.0 : 0.0};
  }
  std::unique_ptr<prism::client::Session> session;
  prism::client::Status s = prism::client::Session::Open(argv[1], rig, {}, &session);
  if (!s.ok()) {
    std::fprintf(stderr, "open: %s\n", s.ToString().c_str());
    return 1;
  }
  std::printf("session %s\n", session->session_id().c_str());
  std::vector<uint8_t> image(160 * 120 * 3);
  for (int i = 0; i < frames; ++i) {
    for (size_t p = 0; p < image.size(); ++p) image[p] = static_cast<uint8_t>((p / 3 + i) % 251);
    s = session->PushFrame(int64_t{i} * 33'000'000, image.data(), 160, 120, 160 * 3);
    if (!s.ok()) std::fprintf(stderr, "frame %d: %s\n", i, s.ToString().c_str());
    prism::client::Event e;
    while (session->Poll(&e, 0)) {
      if (e.kind == prism::client::Event::Kind::kPose)
        std::printf("pose %llu\n", (unsigned long long)e.pose.frame_sequence_number);
      if (e.kind == prism::client::Event::Kind::kError) std::printf("error %s\n", e.error.ToString().c_str());
    }
  }
  prism::client::Summary summary;
  s = session->Close(30000, &summary);
  if (!s.ok()) {
    std::fprintf(stderr, "close: %s\n", s.ToString().c_str());
    return 1;
  }
  std::printf("summary: %llu frames received, %llu keyframes, %zu map points (%s)\n",
              (unsigned long long)summary.frames_received, (unsigned long long)summary.keyframes, session->Map().size(),
              summary.reason.c_str());
  return 0;
}
