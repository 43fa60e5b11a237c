// sdf_checker: load SDF (or URDF) files with the real SDFormat library and print, as one
// JSON document on stdout, every error and what the parser understood: worlds, models with
// their poses resolved by SDFormat's frame graph, links, inertials, visuals and collisions
// with mesh URIs resolved the way simulators resolve them (sdf::findFile with the model://
// search path), joints, lights, physics, spherical coordinates.
//
//   sdf_checker [--path DIR]... [--lenient] FILE...
//
// --path DIR  adds DIR to the model:// search path (like GZ_SIM_RESOURCE_PATH / SDF_PATH).
// By default unrecognised elements and parser warnings are errors (strict); --lenient keeps
// SDFormat's defaults (used for URDF input, whose simulator extensions it only warns about).
// Exit status: 0 when every file loaded with zero errors, 1 otherwise, 2 on bad usage.
// Built by tests/sdf_checker/build.py against libsdformat (pkg-config sdformatNN).

#include <sdf/sdf.hh>

#include <cstdio>
#include <filesystem>
#include <iostream>
#include <sstream>
#include <string>
#include <vector>

namespace {

std::string esc(const std::string &s) {
  std::ostringstream o;
  for (unsigned char c : s) {
    switch (c) {
      case '"': o << "\\\""; break;
      case '\\': o << "\\\\"; break;
      case '\n': o << "\\n"; break;
      case '\r': o << "\\r"; break;
      case '\t': o << "\\t"; break;
      default:
        if (c < 0x20) {
          char b[8];
          std::snprintf(b, sizeof b, "\\u%04x", c);
          o << b;
        } else {
          o << c;
        }
    }
  }
  return o.str();
}

std::string q(const std::string &s) { return "\"" + esc(s) + "\""; }

std::string num(double v) {
  char b[64];
  std::snprintf(b, sizeof b, "%.9g", v);
  std::string s(b);
  if (s == "inf" || s == "-inf" || s == "nan" || s == "-nan") return "null";
  return s;
}

std::string vec(const ignition::math::Vector3d &v) {
  return "[" + num(v.X()) + "," + num(v.Y()) + "," + num(v.Z()) + "]";
}

std::string pose(const ignition::math::Pose3d &p) {
  const auto &e = p.Rot().Euler();
  return "[" + num(p.Pos().X()) + "," + num(p.Pos().Y()) + "," + num(p.Pos().Z()) + "," +
         num(e.X()) + "," + num(e.Y()) + "," + num(e.Z()) + "]";
}

std::string color(const ignition::math::Color &c) {
  return "[" + num(c.R()) + "," + num(c.G()) + "," + num(c.B()) + "," + num(c.A()) + "]";
}

std::string errs(const sdf::Errors &e) {
  std::string s = "[";
  for (size_t i = 0; i < e.size(); ++i) {
    std::ostringstream o;
    o << e[i];
    s += (i ? "," : "") + q(o.str());
  }
  return s + "]";
}

const char *geomType(sdf::GeometryType t) {
  switch (t) {
    case sdf::GeometryType::EMPTY: return "empty";
    case sdf::GeometryType::BOX: return "box";
    case sdf::GeometryType::CYLINDER: return "cylinder";
    case sdf::GeometryType::PLANE: return "plane";
    case sdf::GeometryType::SPHERE: return "sphere";
    case sdf::GeometryType::MESH: return "mesh";
    case sdf::GeometryType::HEIGHTMAP: return "heightmap";
    default: return "other";
  }
}

const char *jointType(sdf::JointType t) {
  switch (t) {
    case sdf::JointType::BALL: return "ball";
    case sdf::JointType::CONTINUOUS: return "continuous";
    case sdf::JointType::FIXED: return "fixed";
    case sdf::JointType::PRISMATIC: return "prismatic";
    case sdf::JointType::REVOLUTE: return "revolute";
    case sdf::JointType::REVOLUTE2: return "revolute2";
    case sdf::JointType::SCREW: return "screw";
    case sdf::JointType::UNIVERSAL: return "universal";
    default: return "other";
  }
}

struct Ctx {
  sdf::ParserConfig config;
  std::vector<std::string> poseErrors;
};

std::string geometry(const sdf::Geometry *g, Ctx &ctx) {
  if (!g) return "null";
  std::string s = "{\"type\":" + q(geomType(g->Type()));
  if (g->Type() == sdf::GeometryType::MESH && g->MeshShape()) {
    const sdf::Mesh *m = g->MeshShape();
    std::string resolved = sdf::findFile(m->Uri(), true, false, ctx.config);
    s += ",\"uri\":" + q(m->Uri()) + ",\"resolved\":" + q(resolved) + ",\"sdf_file\":" + q(m->FilePath()) +
         ",\"scale\":" + vec(m->Scale());
  } else if (g->Type() == sdf::GeometryType::BOX && g->BoxShape()) {
    s += ",\"size\":" + vec(g->BoxShape()->Size());
  } else if (g->Type() == sdf::GeometryType::CYLINDER && g->CylinderShape()) {
    s += ",\"radius\":" + num(g->CylinderShape()->Radius()) + ",\"length\":" + num(g->CylinderShape()->Length());
  } else if (g->Type() == sdf::GeometryType::SPHERE && g->SphereShape()) {
    s += ",\"radius\":" + num(g->SphereShape()->Radius());
  }
  return s + "}";
}

template <typename T>
std::string resolved(const T *obj, const std::string &to, Ctx &ctx) {
  ignition::math::Pose3d p;
  sdf::Errors e = obj->SemanticPose().Resolve(p, to);
  for (const auto &x : e) {
    std::ostringstream o;
    o << x;
    ctx.poseErrors.push_back(o.str());
  }
  return pose(p);
}

std::string link(const sdf::Link *l, Ctx &ctx) {
  const auto &in = l->Inertial();
  std::string s = "{\"name\":" + q(l->Name()) + ",\"pose\":" + resolved(l, "__model__", ctx) +
                  ",\"mass\":" + num(in.MassMatrix().Mass()) +
                  ",\"inertia_diag\":" + vec(in.MassMatrix().DiagonalMoments()) +
                  ",\"inertial_pose\":" + pose(in.Pose()) + ",\"visuals\":[";
  for (uint64_t i = 0; i < l->VisualCount(); ++i) {
    const sdf::Visual *v = l->VisualByIndex(i);
    s += std::string(i ? "," : "") + "{\"name\":" + q(v->Name()) + ",\"pose\":" + pose(v->RawPose()) +
         ",\"geometry\":" + geometry(v->Geom(), ctx);
    if (v->Material()) s += ",\"diffuse\":" + color(v->Material()->Diffuse());
    s += "}";
  }
  s += "],\"collisions\":[";
  for (uint64_t i = 0; i < l->CollisionCount(); ++i) {
    const sdf::Collision *c = l->CollisionByIndex(i);
    s += std::string(i ? "," : "") + "{\"name\":" + q(c->Name()) + ",\"pose\":" + pose(c->RawPose()) +
         ",\"geometry\":" + geometry(c->Geom(), ctx) + "}";
  }
  return s + "]}";
}

std::string model(const sdf::Model *m, const std::string &to, Ctx &ctx) {
  std::string s = "{\"name\":" + q(m->Name()) + ",\"static\":" + (m->Static() ? "true" : "false") +
                  ",\"pose\":" + resolved(m, to, ctx) + ",\"links\":[";
  for (uint64_t i = 0; i < m->LinkCount(); ++i) s += std::string(i ? "," : "") + link(m->LinkByIndex(i), ctx);
  s += "],\"joints\":[";
  for (uint64_t i = 0; i < m->JointCount(); ++i) {
    const sdf::Joint *j = m->JointByIndex(i);
    s += std::string(i ? "," : "") + "{\"name\":" + q(j->Name()) + ",\"type\":" + q(jointType(j->Type())) +
         ",\"parent\":" + q(j->ParentLinkName()) + ",\"child\":" + q(j->ChildLinkName()) +
         ",\"pose\":" + resolved(j, "__model__", ctx);
    if (const sdf::JointAxis *a = j->Axis(0)) {
      ignition::math::Vector3d xyz;
      sdf::Errors e = a->ResolveXyz(xyz, "__model__");
      for (const auto &x : e) {
        std::ostringstream o;
        o << x;
        ctx.poseErrors.push_back(o.str());
      }
      s += ",\"axis_model\":" + vec(xyz) + ",\"lower\":" + num(a->Lower()) + ",\"upper\":" + num(a->Upper()) +
           ",\"effort\":" + num(a->Effort()) + ",\"velocity\":" + num(a->MaxVelocity());
    }
    s += "}";
  }
  s += "],\"models\":[";
  for (uint64_t i = 0; i < m->ModelCount(); ++i)
    s += std::string(i ? "," : "") + model(m->ModelByIndex(i), "__model__", ctx);
  return s + "]}";
}

std::string world(const sdf::World *w, Ctx &ctx) {
  std::string s = "{\"name\":" + q(w->Name()) + ",\"gravity\":" + vec(w->Gravity()) + ",\"physics\":[";
  for (uint64_t i = 0; i < w->PhysicsCount(); ++i) {
    const sdf::Physics *p = w->PhysicsByIndex(i);
    s += std::string(i ? "," : "") + "{\"name\":" + q(p->Name()) + ",\"type\":" + q(p->EngineType()) +
         ",\"max_step_size\":" + num(p->MaxStepSize()) + ",\"default\":" + (p->IsDefault() ? "true" : "false") + "}";
  }
  s += "],\"lights\":[";
  for (uint64_t i = 0; i < w->LightCount(); ++i) {
    const sdf::Light *l = w->LightByIndex(i);
    s += std::string(i ? "," : "") + "{\"name\":" + q(l->Name()) +
         ",\"type\":" + std::to_string(static_cast<int>(l->Type())) +
         ",\"directional\":" + (l->Type() == sdf::LightType::DIRECTIONAL ? "true" : "false") +
         ",\"direction\":" + vec(l->Direction()) + ",\"cast_shadows\":" + (l->CastShadows() ? "true" : "false") + "}";
  }
  s += "]";
  if (const auto *sc = w->SphericalCoordinates()) {
    s += ",\"spherical\":{\"lat\":" + num(sc->LatitudeReference().Degree()) +
         ",\"lon\":" + num(sc->LongitudeReference().Degree()) + ",\"elevation\":" + num(sc->ElevationReference()) + "}";
  }
  s += ",\"models\":[";
  for (uint64_t i = 0; i < w->ModelCount(); ++i) s += std::string(i ? "," : "") + model(w->ModelByIndex(i), "world", ctx);
  return s + "]}";
}

}  // namespace

int main(int argc, char **argv) {
  std::vector<std::string> files, paths;
  bool lenient = false;
  for (int i = 1; i < argc; ++i) {
    std::string a = argv[i];
    if (a == "--path" && i + 1 < argc) {
      paths.push_back(std::filesystem::absolute(argv[++i]).string());
    } else if (a == "--lenient") {
      lenient = true;
    } else if (a == "--version") {
      std::cout << SDF_VERSION_FULL << " (SDF " << SDF_VERSION << ")" << std::endl;
      return 0;
    } else if (!a.empty() && a[0] == '-') {
      std::cerr << "usage: sdf_checker [--path DIR]... [--lenient] FILE..." << std::endl;
      return 2;
    } else {
      files.push_back(std::filesystem::absolute(a).string());
    }
  }
  if (files.empty()) {
    std::cerr << "usage: sdf_checker [--path DIR]... [--lenient] FILE..." << std::endl;
    return 2;
  }
  sdf::Console::Instance()->SetQuiet(true);
  bool ok = true;
  std::cout << "{\"sdformat\":" << q(SDF_VERSION_FULL) << ",\"spec\":" << q(SDF_VERSION) << ",\"files\":[";
  for (size_t f = 0; f < files.size(); ++f) {
    Ctx ctx;
    for (const auto &p : paths) ctx.config.AddURIPath("model://", p);
    ctx.config.SetFindCallback([](const std::string &) { return std::string(); });
    if (!lenient) {
      ctx.config.SetUnrecognizedElementsPolicy(sdf::EnforcementPolicy::ERR);
      ctx.config.SetWarningsPolicy(sdf::EnforcementPolicy::ERR);
    }
    sdf::Root root;
    sdf::Errors e = root.Load(files[f], ctx.config);
    std::string body = ",\"version\":" + q(root.Version()) + ",\"worlds\":[";
    for (uint64_t i = 0; i < root.WorldCount(); ++i) body += std::string(i ? "," : "") + world(root.WorldByIndex(i), ctx);
    body += "],\"model\":";
    body += root.Model() ? model(root.Model(), "", ctx) : std::string("null");
    std::string pe = "[";
    for (size_t i = 0; i < ctx.poseErrors.size(); ++i) pe += (i ? "," : "") + q(ctx.poseErrors[i]);
    pe += "]";
    if (!e.empty() || !ctx.poseErrors.empty()) ok = false;
    std::cout << (f ? "," : "") << "{\"file\":" << q(files[f]) << ",\"errors\":" << errs(e) << ",\"pose_errors\":" << pe
              << body << "}";
  }
  std::cout << "]}" << std::endl;
  return ok ? 0 : 1;
}
